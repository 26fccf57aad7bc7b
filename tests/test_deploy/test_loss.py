"""deploy/loss.py: the one bursty-loss model, which `swarm execute` and the networked agents share."""

import numpy as np
import pytest

from deploy.loss import MAX_BURST_LEN, GilbertElliott, check


def test_the_chain_has_the_loss_and_the_burst_length():
    chain, rng = GilbertElliott(0.3, 4.0), np.random.default_rng(0)
    bad = chain.start(rng.random(20_000))
    states = [bad]
    for _ in range(300):
        bad = chain.step(bad, rng.random(20_000))
        states.append(bad)
    run = np.array(states)  # [T, links]
    assert abs(run.mean() - 0.3) < 0.01  # stationary from the first message
    ends = (run[:-1] & ~run[1:]).sum()  # a burst ends where bad turns good
    assert abs(run[:-1].sum() / ends - 4.0) < 0.1


def test_the_executor_and_the_network_draw_from_the_same_chain():
    from deploy.executor import MessageBus
    from deploy.net.faults import FaultSpec, LinkFaults

    bus = MessageBus(1, 3, 1, burst_loss=0.3, burst_len=4.0)
    link = LinkFaults(FaultSpec(burst_loss=0.3, burst_len=4.0), receiver=0, round_deadline=1.0)
    for chain in (bus._burst, link._burst):
        assert isinstance(chain, GilbertElliott) and chain.to_good == 0.25


@pytest.mark.parametrize(
    "loss, length", [(1.0, 4.0), (-0.1, 4.0), (0.3, 0.5), (0.3, float("inf")), (0.3, float("nan"))]
)
def test_bad_parameters_are_refused_naming_the_option(loss, length):
    with pytest.raises(ValueError, match="--burst-(loss|len)"):
        check(loss, length)
    assert MAX_BURST_LEN >= 1e3
