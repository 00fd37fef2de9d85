"""The fuzz runner's bookkeeping, without a controller: which suspects a trigger keeps. A runner
is built on two free loopback ports; nothing is sent."""
from __future__ import annotations

from pathlib import Path

import pytest
from loopback import free_ports
from vm110.fuzz import cases as K
from vm110.fuzz.oracles import STALL, Trigger
from vm110.fuzz.runner import RunConfig, Runner
from vm110.fuzz.session import Settings


@pytest.fixture
def runner(tmp_path: Path):
    rx, listen = free_ports(2)
    made = Runner(RunConfig(settings=Settings(("127.0.0.1", rx), ("127.0.0.1", listen)), out=tmp_path / "out"))
    yield made
    made.session.close()


def test_a_lost_controller_keeps_more_suspects_than_are_replayed(runner):
    """Trial: without --target-cmd the stall's culprit was the 13th suspect and was cut from
    suspect_cases, the only clue left."""
    for i in range(30):
        runner.records[i] = (K.generate(1, i), [])
    runner._unreproduced(Trigger(STALL, 0.0, "no VRPO", suspects=list(range(30))), list(range(30)), "gone")
    [entry] = runner.unreproduced
    assert entry["suspects"] == list(range(30))
    assert entry["suspect_cases"] == [K.generate(1, i).description for i in range(30)]
