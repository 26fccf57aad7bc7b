"""Build models/index.toml, the model zoo's index, from the spec results under results/.

    python tools/make_zoo.py            # write models/index.toml
    python tools/make_zoo.py --check    # exit 1 if the written index differs from a rebuild

One entry per published setting: each task x UC/RC x M = 3, 5, 6, 7, 10 from the recipe
spec (seed 0), the transfer policy from the beyond spec, the robust policy, and the large-team
policies on the agents' auction by radio (tools/radio_recipe.sh). Where the recipe has two
policies of one setting (a Table 1 run and a curriculum stage of the same size), the entry
is the one with the higher S% on its 500 fresh episodes, the Table 1 run on a tie. Then
``swarm models --render`` writes the cards and models/README.md from the index.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from reproduce.cells import cell_dir, policy_path  # noqa: E402
from reproduce.spec import load_spec  # noqa: E402
from trainer.zoo import INDEX, file_sha256  # noqa: E402

TASKS = ("coverage", "formation", "line")
COMMS = ("uc", "rc")
SIZES = (3, 5, 6, 7, 10)
RECIPE_ROOT = "results/reproduce-recipe"
RADIO_ROOT = "results/radio"
# the large-team policies on the agents' own auction by messages (landmark_order radio):
# tools/radio_recipe.sh TASK trains M = 10 from scratch, then M = 100 from it, and evaluates
# (M >= 100: 100 episodes at seed 777, with the fraction covered beside S%)
RADIO = ("coverage-rc-m100-radio", "line-rc-m100-radio", "formation-rc-m100-radio")
BEYOND_ROOT = "results/reproduce-beyond"
# the transfer policy: M = 3 and 4 trained together (beyond spec), the seed of four whose
# M = 3 policy carried furthest to M = 5 on 500 fresh episodes (x-zs-coverage-uc-m34)
TRANSFER = ("x-coverage-uc-m34", 7, "x-zs-coverage-uc-m34")
# single cells published as they are: (zoo name, spec, its results, cell, stage M of a curriculum)
SINGLES = (
    ("coverage-rc-m5-robust", "recipe", RECIPE_ROOT, "f-coverage-rc-m5-rounds", 0,
     "coverage RC M = 5: the zoo's, trained on through message losses per round (f-coverage-rc-m5-rounds)"),
)  # fmt: skip


USES = {
    "coverage-rc-m5-robust": "Use it for coverage RC at M = 5 where messages are lost: trained on through independent "
    "losses of up to 30% per round.",
}


def _rel(path: str) -> str:
    return os.path.relpath(path, ROOT)


def _result(root: str, cell, seed: int) -> dict:
    with open(os.path.join(ROOT, cell_dir(root, cell, seed), "result.json")) as f:
        return json.load(f)


def _paper_s(cell, agents: int):
    s = cell.paper.get(str(agents), {}).get("S")
    return None if s is None else s / 100


def _zero_shot(rows: list[dict]) -> dict:
    return {int(r["agents"]): round(r["success_rate"], 4) for r in rows}


def candidates(spec, task: str, comm: str, agents: int) -> list[dict]:
    """Every recipe policy of one setting, as index entries (Table 1 runs first)."""
    cells = {c.id: c for c in spec.cells}
    found = []
    t1 = cells.get(f"t1-{task}-{comm}-m{agents}")
    if t1 is not None and os.path.exists(os.path.join(ROOT, cell_dir(RECIPE_ROOT, t1, 0), "result.json")):
        row = _result(RECIPE_ROOT, t1, 0)["rows"][0]
        zs_path = os.path.join(ROOT, cell_dir(RECIPE_ROOT, t1, 0), "zero-shot-500.json")
        zero_shot = {}
        if os.path.exists(zs_path):
            with open(zs_path) as f:
                zero_shot = _zero_shot(json.load(f)["results"])
        found.append(_entry(t1, 0, agents, row, policy_path(RECIPE_ROOT, t1, 0), zero_shot, (agents,)))
    chain_id = f"t2-coverage-emp-{comm}" if task == "coverage" else f"t3-{task}-{comm}"
    chain = cells.get(chain_id)
    if chain is not None and agents in chain.run.sizes:
        rows = {r["agents"]: r for r in _result(RECIPE_ROOT, chain, 0)["rows"]}
        if agents in rows:
            zero_shot = {}
            for zs in spec.cells:  # a zero-shot row of this stage (Table 4)
                if zs.kind == "zero-shot" and zs.needs == chain.id and (zs.run.source_agents or 5) == agents:
                    zero_shot = _zero_shot(_result(RECIPE_ROOT, zs, 0)["rows"])
            trained_on = tuple(m for m in chain.run.sizes if m <= agents)
            path = policy_path(RECIPE_ROOT, chain, 0, agents)
            found.append(_entry(chain, 0, agents, rows[agents], path, zero_shot, trained_on))
    return found


def _entry(cell, seed: int, agents: int, row: dict, weights: str, zero_shot: dict, trained_on: tuple) -> dict:
    spec_name = weights.split("/")[1].removeprefix("reproduce-")
    curves = os.path.join(os.path.dirname(weights), "curves.png")
    if not os.path.exists(os.path.join(ROOT, curves)):  # a polish's curves are its stage's
        curves = os.path.join(os.path.dirname(os.path.dirname(weights)), "curves.png")
    return {
        "task": cell.run.task,
        "comm": cell.run.comm,
        "agents": agents,
        "comm_radius": cell.run.comm_radius,
        "entity_mode": cell.run.config.model.entity_mode,
        "weights": weights,
        "sha256": file_sha256(os.path.join(ROOT, weights)),
        "spec": spec_name,
        "cell": cell.id,
        "seed": seed,
        "trained_on": list(trained_on),
        "success": row["success_rate"],
        "mean_length": round(row["mean_length"], 3),
        "dist": None if row.get("dist") is None else round(row["dist"], 4),
        "covered": None if row.get("covered") is None else round(row["covered"], 4),
        "episodes": row.get("episodes", 500),
        "eval_seed": row.get("seed", 777),
        "paper_success": _paper_s(cell, agents),
        "updates": int(row.get("updates", 0)) + int(row.get("polish_updates", 0)),
        "env_steps": int(row.get("env_steps", 0)),
        "minutes": round(row.get("wall_time", 0.0) / 60, 1),
        "zero_shot": zero_shot,
        "curves": curves if os.path.exists(os.path.join(ROOT, curves)) else "",
    }


def build() -> list[dict]:
    recipe = load_spec("recipe")
    entries = []
    for task in TASKS:
        for comm in COMMS:
            for agents in SIZES:
                found = candidates(recipe, task, comm, agents)
                if not found:
                    print(f"no recipe result for {task} {comm} M = {agents}", file=sys.stderr)
                    continue
                best = max(found, key=lambda e: e["success"])  # max keeps the first (Table 1) on a tie
                how = "trained from scratch" if best["cell"].startswith("t1-") else "the curriculum stage"
                if best["cell"].startswith("t1-") and recipe.cell(best["cell"]).needs:
                    how = "fine-tuned from another cell's policy"
                best["summary"] = f"{task} {comm.upper()} M = {agents}: {how} ({best['cell']})"
                entries.append({"name": f"{task}-{comm}-m{agents}", **best})
    beyond = load_spec("beyond")
    cells = {c.id: c for c in beyond.cells}
    train_id, seed, zs_id = TRANSFER
    cell = cells[train_id]
    row = _result(BEYOND_ROOT, cell, seed)["rows"][0]
    zero_shot = _zero_shot(_result(BEYOND_ROOT, cells[zs_id], seed)["rows"])
    entry = _entry(
        cell, seed, cell.run.agents, row, policy_path(BEYOND_ROOT, cell, seed), zero_shot, cell.run.config.team_sizes
    )
    entry["summary"] = "coverage UC, trained on M = 3 and 4 together: the M = 3 policy that carries furthest to M = 5"
    entry["use"] = "Use it to run one small coverage UC policy at M = 3 to 5 with no fine-tuning (zero-shot)."
    entries.append({"name": "coverage-uc-m3-transfer", **entry})
    for name, spec_name, root, cell_id, stage, summary in SINGLES:
        cell = load_spec(spec_name).cell(cell_id)
        if not os.path.exists(os.path.join(ROOT, cell_dir(root, cell, 0), "result.json")):
            print(f"no result for {cell_id}", file=sys.stderr)
            continue
        rows = {r["agents"]: r for r in _result(root, cell, 0)["rows"]}
        agents = stage or cell.run.agents
        trained_on = [m for m in cell.run.sizes if m <= agents] if stage else [agents]
        weights = _rel(os.path.join(ROOT, policy_path(root, cell, 0, stage)))
        entry = _entry(cell, 0, agents, rows[agents], weights, {}, trained_on)
        entries.append({"name": name, **entry, "summary": summary, "use": USES[name]})
    for name in RADIO:
        entry = radio_entry(name)
        if entry is not None:
            entries.append(entry)
    return entries


def radio_entry(name: str) -> dict | None:
    run = os.path.join(RADIO_ROOT, name)
    paths = {k: os.path.join(ROOT, run, f) for k, f in (("eval", "eval-777.json"), ("summary", "summary.json"))}
    if not all(os.path.exists(p) for p in paths.values()):
        print(f"no result for {name}", file=sys.stderr)
        return None
    with open(paths["eval"]) as f:
        row = json.load(f)
    with open(paths["summary"]) as f:
        summary = json.load(f)
    with open(os.path.join(ROOT, run, "config.json")) as f:
        config = json.load(f)
    small = os.path.join(ROOT, os.path.dirname(config["init_from"]), "summary.json")  # the M = 10 cell
    with open(small) as f:
        first = json.load(f)
    weights = os.path.join(run, "policy.pt")
    task = config["task"]
    return {
        "name": name,
        "task": task,
        "comm": config["comm"],
        "agents": config["agents"],
        "comm_radius": config["comm_radius"],
        "entity_mode": config["model"]["entity_mode"],
        "weights": weights,
        "sha256": file_sha256(os.path.join(ROOT, weights)),
        "spec": "radio",
        "cell": name,
        "seed": 0,
        "trained_on": [10, config["agents"]],
        "success": row["success_rate"],
        "mean_length": round(row["mean_length"], 3),
        "dist": None if row.get("dist") is None else round(row["dist"], 4),
        "covered": None if row.get("covered") is None else round(row["covered"], 4),
        "episodes": row["episodes"],
        "eval_seed": row["seed"],
        "updates": first["update"] + summary["update"],
        "env_steps": first["env_steps"] + summary["env_steps"],
        "minutes": round((first["wall_time"] + summary["wall_time"]) / 60, 1),
        "zero_shot": {},
        "curves": os.path.join(run, "curves.png"),
        "summary": f"trained from scratch at M = 10 ({first['update']} updates), then {summary['update']} at "
        f"M = {config['agents']}, on the agents' own auction by messages (landmark_order radio, "
        f"{config['auction_rounds']} rounds a step, tables of the {config['landmark_neighbours']} nearest landmarks)",
        "use": f"Use it for {task} RC teams of about {config['agents']} where coordination must travel by radio: "
        f"each agent's landmark comes from an auction the agents run by messages to the teammates they hear "
        f"within comm radius {config['comm_radius']:g}; it senses the landmarks within "
        f"{config['sense_radius']:g} and, for each, how near its nearest other agent is (occupancy).",
    }


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()) + " }"
    return repr(value)


def to_toml(entries: list[dict]) -> str:
    lines = [
        "# The model zoo: one curated policy per setting. Generated by `python tools/make_zoo.py`",
        "# from the spec results under results/ (do not edit by hand); cards and models/README.md",
        "# by `swarm models --render`. S% (success) on 500 fresh greedy episodes at seed 777.",
        "",
    ]
    for e in entries:
        lines.append("[[model]]")
        for key, value in e.items():
            if value is None:
                continue  # TOML has no null: an absent key is the entry's default (None)
            lines.append(f"{key} = {_toml_value(value)}")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="compare the index with a rebuild; exit 1 on a difference")
    args = parser.parse_args(argv)
    text = to_toml(build())
    if args.check:
        with open(INDEX) as f:
            same = f.read() == text
        print("models/index.toml is up to date" if same else "models/index.toml differs from a rebuild")
        return 0 if same else 1
    from taichi_swarm.files import atomic_write_bytes

    os.makedirs(os.path.dirname(INDEX), exist_ok=True)
    atomic_write_bytes(INDEX, lambda f: f.write(text.encode()))
    print(f"wrote {_rel(INDEX)}: {text.count('[[model]]')} entries")
    return 0


if __name__ == "__main__":
    sys.exit(main())
