"""Suite-wide settings and fixtures."""
from __future__ import annotations

import os
import shutil
import subprocess
import uuid
from typing import Iterator

import pytest
from hypothesis import settings

import report_schema
import sessionwide
import tshark_runner as T
import vm110.analysis

# Every report a test makes must match docs/report.schema.json: those analyze() returns (wrapped
# here, before any test module imports it) and those `vm110 analyze --json` writes (below).
vm110.analysis.analyze = report_schema.validating(vm110.analysis.analyze)

# CI runs the same examples every time, so that a red run is reproducible; locally they vary.
settings.register_profile("ci", derandomize=True, deadline=None)
settings.register_profile("dev", deadline=None)
settings.load_profile("ci" if os.environ.get("CI") else "dev")


@pytest.fixture(scope="session", autouse=True)
def _sessionwide(tmp_path_factory) -> None:
    """The folder the workers share work in (tests/sessionwide.py)."""
    sessionwide.start(tmp_path_factory.getbasetemp())


@pytest.fixture(autouse=True)
def _written_reports_match_the_schema(request) -> Iterator[None]:
    """After each test, every JSON report written under its tmp_path matches the schema."""
    folder = request.getfixturevalue("tmp_path") if "tmp_path" in request.fixturenames else None
    yield
    if folder is not None:
        report_schema.check_written(folder)


@pytest.fixture
def netns() -> Iterator[str]:
    """A network namespace of the test's own whose only interface is its loopback, with multicast
    routed there: multicast tests never reach a real interface. Skips without root or iproute2."""
    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("needs root and iproute2 to make a network namespace")
    name = f"vm110-{uuid.uuid4().hex[:8]}"
    if subprocess.run(["ip", "netns", "add", name], capture_output=True).returncode != 0:
        pytest.skip("cannot create a network namespace here")
    try:
        for cmd in (["link", "set", "lo", "up"], ["link", "set", "lo", "multicast", "on"],
                    ["route", "add", "224.0.0.0/4", "dev", "lo"]):
            subprocess.run(["ip", "-n", name, *cmd], check=True, capture_output=True)
        yield name
    finally:
        subprocess.run(["ip", "netns", "del", name], capture_output=True)


@pytest.fixture(params=T.RUNNERS, ids=lambda r: r.name)
def ws(request, tmp_path) -> Iterator[T.Workspace]:
    """A workspace of each tshark the dissector is tested on; a missing one fails the test."""
    try:
        with request.param.workspace(tmp_path) as workspace:
            yield workspace
    except T.TsharkUnavailable as exc:
        pytest.fail(str(exc))
