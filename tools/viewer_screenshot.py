"""Screenshot of a recording in Rerun's web viewer, headless, to check the layout as a
person would see it (not part of the test suite: it needs Chromium and ~40 s).

    apt-get install -y chromium && pip install playwright     # once; no browser download
    swarm eval results/coverage-m3-uc/policy.pt --episodes 8 --record /tmp/eval.rrd
    python tools/viewer_screenshot.py /tmp/eval.rrd docs/media/viewer-grid.png

Serves the file with the `rerun` binary that ships with rerun-sdk (`--serve-web` on
127.0.0.1), opens it in Debian's Chromium through Playwright (software rendering), waits
for the viewer to load and writes a PNG: one 2D panel per recorded environment in a grid
over the reward / success plot (deploy/recording.py `layout`).
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import time
import urllib.parse

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from deploy.replay import rerun_command  # noqa: E402

CHROMIUM_FLAGS = [
    "--no-sandbox",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--enable-unsafe-swiftshader",
    "--use-angle=swiftshader",
    "--ignore-gpu-blocklist",
]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("recording", help="a .rrd file written by --record")
    ap.add_argument("out", help="PNG to write")
    ap.add_argument("--chromium", default="/usr/bin/chromium")
    ap.add_argument("--wait", type=float, default=30.0, help="seconds to let the viewer load (default 30)")
    args = ap.parse_args(argv)
    if not os.path.isfile(args.recording):
        ap.error(f"{args.recording} does not exist")
    if not os.path.exists(args.chromium):
        ap.error(f"no Chromium at {args.chromium} (apt-get install -y chromium)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        ap.error("needs playwright: pip install playwright (it drives the system Chromium; no download)")
    grpc, web = free_port(), free_port()
    server = subprocess.Popen(
        rerun_command()
        + [args.recording, "--serve-web", "--bind", "127.0.0.1", "--port", str(grpc), "--web-viewer-port", str(web)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        time.sleep(3)
        source = urllib.parse.quote(f"rerun+http://127.0.0.1:{grpc}/proxy", safe="")
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=args.chromium, headless=True, args=CHROMIUM_FLAGS)
            page = browser.new_page(viewport={"width": 1400, "height": 900})
            page.goto(f"http://127.0.0.1:{web}?url={source}")
            time.sleep(args.wait)
            page.screenshot(path=args.out)
            browser.close()
    finally:
        server.kill()
        server.wait()
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
