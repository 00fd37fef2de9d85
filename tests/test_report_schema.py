"""The analysis report's JSON Schema (docs/report.schema.json): a valid draft 2020-12 schema,
shipped in the package and printed by `vm110 analyze --schema`, strict enough to catch a report
that changed shape, and naming the same keys as docs/report.md. (That every report the suite makes
matches it is checked where they are made: tests/conftest.py.)"""
from __future__ import annotations

import copy
import json
import re
import subprocess
import sys
from dataclasses import fields
from pathlib import Path

import jsonschema
import pytest

import report_schema
from vm110 import resources
from vm110.analysis import analyze
from vm110.analysis.findings import FINDINGS, TOTAL_NAMES
from vm110.analysis.report import SCHEMA_VERSION, Options

REPO = Path(__file__).resolve().parents[1]
CAPTURES = REPO / "captures"
DOC = REPO / "docs" / "report.md"
SCHEMA = report_schema.SCHEMA
DEFS = SCHEMA["$defs"]
PUBLISHED = jsonschema.Draft202012Validator(SCHEMA)
ITEM_BASE = {"frame", "frames", "time", "filter"}


def vm110(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vm110", *args], capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def report() -> dict:
    """A report with findings of many kinds: restarts, lost, duplicates, commands interrupted."""
    return json.loads(json.dumps(analyze(str(CAPTURES / "restart.pcapng"))))


def test_the_schema_is_a_valid_draft_2020_12_schema():
    assert SCHEMA["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    jsonschema.Draft202012Validator.check_schema(SCHEMA)
    # Its id names the version it describes (trial: still ':3' at schema_version 5).
    assert SCHEMA["$id"] == f"urn:vm110:analysis-report:{SCHEMA_VERSION}"


def test_analyze_prints_the_schema_the_package_ships():
    done = vm110("analyze", "--schema")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == SCHEMA
    assert resources.report_schema().read_bytes() == report_schema.SCHEMA_PATH.read_bytes()


def test_analyze_without_a_capture_is_a_usage_error():
    done = vm110("analyze")
    assert done.returncode == 2 and done.stderr.strip() == "vm110 analyze: give at least one CAPTURE (or --schema)"


def test_reports_of_one_and_of_several_captures_validate(tmp_path, report):
    report_schema.check(report)
    out = tmp_path / "several.json"
    done = vm110("analyze", str(CAPTURES / "restart.pcapng"), str(tmp_path / "missing.pcap"), "--quiet",
                 "--json", str(out))
    assert done.returncode == 2            # one capture unreadable: an error entry beside the report
    document = json.loads(out.read_text())
    assert document["errors"] and len(document["reports"]) == 1
    report_schema.check(document)
    assert report_schema.check_written(tmp_path) == 1


@pytest.mark.parametrize("change, where", [
    (lambda r: r.update(surprise=1), "$"),                                              # unknown key
    (lambda r: r["capture"].pop("packets"), "$.capture"),                               # missing key
    (lambda r: r["capture"].update(packets=-1), "$.capture.packets"),                   # negative count
    (lambda r: r["capture"].update(format="erf"), "$.capture.format"),                  # outside the enum
    (lambda r: r["totals"].update(lost="3"), "$.totals.lost"),                          # wrong type
    (lambda r: r["verdict"]["findings"][0].update(rule="lots"), "$.verdict.findings[0].rule"),
    (lambda r: r["verdict"]["findings"][0].update(severity="note"), "$.verdict.findings[0].severity"),
    (lambda r: r["senders"][0]["serial"].update(scope="global"), "$.senders[0].serial.scope"),
    (lambda r: r["commands"]["VRCI"]["list"].append({"sender": "x"}), "$.commands.VRCI.list"),
    (lambda r: r["periodic"][0].update(bursts=3), "$.periodic[0]"),                      # VRPI has no bursts
])
def test_the_schema_rejects_a_report_of_another_shape(report, change, where):
    broken = copy.deepcopy(report)
    assert broken["periodic"][0]["type"] == "VRPI" and broken["verdict"]["findings"]
    change(broken)
    found = report_schema.problems(broken)
    assert found and any(p.startswith(where) for p in found), found
    # (the suite's validator has the $refs inlined: the schema as published judges alike)
    assert PUBLISHED.is_valid(report) and not PUBLISHED.is_valid(broken)


def test_an_item_must_carry_the_details_of_its_rule(report):
    """A finding's items are checked by its rule: a `lost` item without `count`, or with a key of
    another rule, is rejected; the severity is the rule's."""
    findings = {f["rule"]: i for i, f in enumerate(report["verdict"]["findings"])}
    assert "lost" in findings
    for change in (lambda item: item.pop("count"), lambda item: item.update(command_id=3)):
        broken = copy.deepcopy(report)
        change(broken["verdict"]["findings"][findings["lost"]]["items"][0])
        assert report_schema.problems(broken)
    broken = copy.deepcopy(report)
    broken["verdict"]["findings"][findings["lost"]]["severity"] = "warning"
    assert report_schema.problems(broken)


def test_enumerations_follow_the_code():
    """Rules and their severities, totals and options: the schema lists exactly what the code makes."""
    severity = {rule: sev for rule, sev, *_ in FINDINGS} | {"damaged": "error", "no_eglink": "error", "ip_fragments": "warning",
                                                            "unread_link_type": "warning", "tunnels": "warning",
                                                            "not_in_time_order": "warning", "capture_dropped": "warning"}
    assert set(DEFS["finding"]["properties"]["rule"]["enum"]) == set(severity)
    assert {c["if"]["properties"]["rule"]["const"]: c["then"]["properties"]["severity"]["const"]
            for c in DEFS["finding"]["allOf"]} == severity
    assert list(DEFS["totals"]["properties"]) == list(TOTAL_NAMES)
    assert set(DEFS["options"]["properties"]) == {f.name for f in fields(Options)}


# --- docs/report.md and the schema name the same keys ---------------------------------------------
def _expand(path: str) -> list[str]:
    """`a.{b,c}.d` -> a.b.d, a.c.d; `<name>` (a map's keys) -> <*>."""
    path = re.sub(r"<[^>]+>(/<[^>]+>)?", "<*>", path)
    found = re.search(r"\{([^{}]*)\}", path)
    if not found:
        return [path]
    return [p for alt in found[1].split(",") for p in _expand(path[:found.start()] + alt + path[found.end():])]


def _closed(paths: set[str]) -> set[str]:
    """The paths and every prefix of them (a.b[].c -> a, a.b, a.b[], a.b[].c)."""
    out = set()
    for p in paths:
        for i, ch in enumerate(p):
            if ch == "." or p.startswith("[]", i):
                out.add(p[:i])
        out.add(p)
    return out


def _doc_tables() -> dict[str, list[list[str]]]:
    """The tables of the JSON report section, by subsection: rows of cells."""
    text = DOC.read_text()
    section = text[text.index("## JSON report"):]
    section = section[:section.index("\n## ", 3)]
    tables: dict[str, list[list[str]]] = {}
    heading = ""
    for line in section.splitlines():
        if line.startswith("### "):
            heading = line[4:].strip()
        elif line.startswith("| ") and not line.startswith("| ---"):
            tables.setdefault(heading, []).append([c.strip() for c in line.strip("|").split("|")])
    return {h: rows[1:] for h, rows in tables.items()}          # without the header row


def _doc_keys(rows: list[list[str]]) -> set[str]:
    return _closed({p for row in rows for key in re.findall(r"`([^`]+)`", row[0]) for p in _expand(key)})


def _schema_keys(node: dict, path: str = "", out: set | None = None) -> set[str]:
    out = set() if out is None else out
    if "$ref" in node:
        node = DEFS[node["$ref"].rsplit("/", 1)[1]]
    for option in node.get("anyOf", []):
        _schema_keys(option, path, out)
    for key, sub in node.get("properties", {}).items():
        child = f"{path}.{key}" if path else key
        out.add(child)
        if isinstance(sub, dict):
            _schema_keys(sub, child, out)
    if isinstance(node.get("items"), dict):             # a list of records (not of numbers)
        below = _schema_keys(node["items"], path + "[]", set())
        out |= below | ({path + "[]"} if below else set())
    if isinstance(node.get("additionalProperties"), dict) and not node.get("properties"):
        out.add(path + ".<*>")
        _schema_keys(node["additionalProperties"], path + ".<*>", out)
    return out


def _different(doc: set[str], schema: set[str]) -> dict:
    return {"only in docs/report.md": sorted(doc - schema), "only in the schema": sorted(schema - doc)}


def test_report_md_and_the_schema_name_the_same_keys():
    tables = _doc_tables()
    doc = _doc_keys(tables["One capture"])
    schema = _schema_keys(DEFS["report"])
    assert doc == schema, _different(doc, schema)
    doc = _doc_keys(tables["Several captures"])
    schema = _schema_keys(DEFS["several"], out=set())
    schema = {k for k in schema if not k.startswith(("reports[].", "combined.totals.", "combined.captures[].totals."))}
    assert doc == schema, _different(doc, schema)


def test_report_md_and_the_schema_give_each_rule_the_same_item_keys():
    rows = _doc_tables()["Where a finding lies"]
    doc = {row[0].strip("`"): (row[1], set(re.findall(r"`([^`]+)`", row[2]))) for row in rows}
    severity = {c["if"]["properties"]["rule"]["const"]: c["then"]["properties"]["severity"]["const"]
                for c in DEFS["finding"]["allOf"]}
    assert set(doc) == set(severity)
    for rule, (sev, keys) in doc.items():
        assert sev == severity[rule], rule
        item = DEFS.get(f"item_{rule}")
        schema_keys = set() if item is None else set(item["properties"]) - ITEM_BASE
        assert keys == schema_keys, (rule, _different(keys, schema_keys))
