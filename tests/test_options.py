"""Issue 17, "every bad value refused": every numeric option of every subcommand, found by walking
the parser itself, so that an option added later is tried without anyone remembering to.

NaN, +inf, -inf, -1, 0 and 1e18 are tried on each; a value is either refused (exit 2, one line
`vm110 <cmd>: ...` naming the option) or listed in ACCEPTED because the option's help documents it
as valid. Nothing here starts real work: analyze and decode run in-process on a capture that does
not exist, synth on a scenario that does not exist (an accepted value ends there); simulate and
fuzz are only parsed, never run, so nothing is sent.
"""
from __future__ import annotations

import argparse
from typing import Iterator, Optional

import pytest

from vm110 import cli
from vm110.commands import simulate
from vm110.errors import CliError
from vm110.numbers import FieldsType, NumberType, fields, number, port, span

BAD = ("nan", "inf", "-inf", "-1", "0", "1e18")
MISSING = "/nonexistent/vm110-missing.pcap"
# How an accepted value ends without work, per command; commands not listed are only parsed.
RUN_UNTIL = {
    "analyze": ([MISSING], MISSING),
    "decode": ([MISSING], MISSING),
    "monitor": (["--read", MISSING], MISSING),
    "synth": (["no-such-scenario", "--out", "/nonexistent/out.pcap"], "unknown scenario"),
    "fleet": ([MISSING, "--out", "/nonexistent/vm110-fleet"], MISSING),
}
_SIMULATE = {"--seed": {"0", "1e18"}, "--stop-at": {"0"}, "--restart": {"0", "0:0"}, "--restart-serial": {"0"},
             "--serial-start": {"0"}, "--command-id-start": {"0"}, "--command-every": {"0"},
             **{option: {"0"} for option in ("--loss", "--duplicate", "--mirror", "--reorder", "--corrupt",
                                             "--delay", "--jitter")}}
# Values among the tried ones that an option's help documents as valid.
ACCEPTED: dict[tuple[str, str], set[str]] = {
    ("analyze", "--vrpo-start"): {"0"},
    ("analyze", "--vrpo-data-size"): {"0"},
    ("monitor", "--vrpo-start"): {"0"},
    ("monitor", "--vrpo-data-size"): {"0"},
    **{("monitor", option): {"0"} for option in ("--before", "--after", "--idle")},
    ("fleet build", "--vrpo-start"): {"0"},
    ("fleet build", "--vrpo-data-size"): {"0"},
    ("synth", "--seed"): {"0", "1e18"},
    ("synth", "--vrpo-start"): {"0"},
    ("fuzz", "--seed"): {"0", "1e18"},
    ("fuzz", "--memory-growth"): {"0"},     # (its help: 0 turns the growth rule off)
    **{("simulate bu", option): values for option, values in {
        **_SIMULATE, "--unarmed-rus": {"0"}, "--origin": {"0"}, "--vrpo-start": {"0"}}.items()},
    **{("simulate controller", option): values
       for option, values in {**_SIMULATE, "--data-size": {"0"}, "--vrpo-start": {"0"}}.items()},
}


def leaf_parsers(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()) -> Iterator[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    """(command words, parser) of every parser that takes options (simulate bu, simulate controller...)."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield path, parser
    for action in subs:
        for name, sub in action.choices.items():
            yield from leaf_parsers(sub, (*path, name))


def typed_options() -> list[tuple[tuple[str, ...], argparse.Action]]:
    return [(path, action) for path, parser in leaf_parsers(cli.build_parser())
            for action in parser._actions if action.type is not None]


def tries(action: argparse.Action) -> Iterator[tuple[str, list[str]]]:
    """(value tried, its arguments): each bad value alone; for START:END-like values also after a
    valid first field; for several numbers (MIN MAX) in each place, the others at their defaults."""
    kind = action.type
    for value in BAD:
        text = str(10**18) if value == "1e18" and getattr(kind, "integer", False) else value
        if isinstance(kind, FieldsType):
            yield value, [f"{action.option_strings[0]}={text}"]
            yield f"0:{value}", [f"{action.option_strings[0]}=0:{text}"]
        elif isinstance(action.nargs, int):
            for place in range(action.nargs):
                values = [str(d) for d in action.default]
                values[place] = text
                yield value, [action.option_strings[0], *values]
        else:
            yield value, [f"{action.option_strings[0]}={text}"]     # "=": -inf is not an option


CASES = [pytest.param(path, action.option_strings[0], value, args, id=f"{' '.join(path)} {' '.join(args)}")
         for path, action in typed_options() for value, args in tries(action)]


def outcome(capsys, path: tuple[str, ...], args: list[str]) -> tuple[int, str, Optional[str]]:
    """Exit code, standard error, and the text an accepted value ends with (None: parsed only)."""
    base, sentinel = RUN_UNTIL.get(path[0], ([], None))
    return (*in_process(capsys, [*path, *args, *base], run=sentinel is not None), sentinel)


def in_process(capsys, argv: list[str], run: bool = True) -> tuple[int, str]:
    """Exit code and standard error of `vm110 ARGV`, run or only parsed."""
    try:
        code = cli.main(argv) if run else (cli.build_parser().parse_args(argv) and 0)
    except SystemExit as exc:
        code = exc.code
    return code, capsys.readouterr().err


def refused_in_one_line(code: int, err: str, path: tuple[str, ...], option: str) -> str:
    assert code == 2 and "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"vm110 {path[0]}: ") and option in lines[0], lines[0]
    return lines[0]


# What each command needs before an unknown argument is the only thing wrong (dissect passes what
# follows its capture to tshark).
NEEDS = {"analyze": ["c.pcap"], "craft": ["--out", "o.pcap"], "decode": ["c.pcap"], "fleet": ["query", "d"],
         "monitor": ["--read", "c.pcap"], "simulate": ["bu"], "wireshark": ["path"]}


@pytest.mark.parametrize("command", sorted(set(cli.COMMANDS) - {"dissect"}))
def test_an_unknown_argument_is_told_by_its_command(capsys, command):
    # (argparse leaves it to the top parser: "vm110: unrecognized arguments")
    code, err = in_process(capsys, [command, *NEEDS.get(command, []), "--no-such-option"])
    refused_in_one_line(code, err, (command,), "unrecognized arguments: --no-such-option")


@pytest.mark.parametrize("path, option, value, args", CASES)
def test_every_numeric_option_refuses_bad_values(capsys, path, option, value, args):
    code, err, sentinel = outcome(capsys, path, args)
    if value in ACCEPTED.get((" ".join(path), option), ()):
        assert code == (2 if sentinel else 0) and (sentinel or "") in err and option not in err, err
    else:
        refused_in_one_line(code, err, path, option)


def test_the_walk_finds_every_command_s_options():
    found = {(" ".join(path), action.option_strings[0]) for path, action in typed_options()}
    assert {("analyze", "--vrpo-range"), ("analyze", "--port"), ("decode", "--port"), ("synth", "--duration"),
            ("fuzz", "--rate"), ("simulate bu", "--delay"), ("simulate controller", "--outage")} <= found
    assert set(ACCEPTED) <= found, set(ACCEPTED) - found      # no stale entries


@pytest.mark.parametrize("path, action", [pytest.param(p, a, id=f"{' '.join(p)} {a.option_strings[0]}")
                                          for p, a in typed_options()])
def test_every_numeric_option_is_a_validated_number_with_its_range_in_the_help(path, action):
    assert isinstance(action.type, (NumberType, FieldsType)), \
        f"{action.option_strings[0]}: use vm110.numbers.number (finite, ranged, unit in the help)"
    assert action.help and action.type.range_text in action.help, action.help


@pytest.mark.parametrize("path, args, option", [
    (("analyze",), ["--vrpo-range", "200", "50"], "--vrpo-range"),
    (("simulate", "bu"), ["--outage", "5:2"], "--outage"),
    (("simulate", "controller"), ["--stall", "3:3"], "--stall"),
    (("simulate", "controller"), ["--glink", "2:1"], "--glink"),
    (("simulate", "bu"), ["--restart", "3:70000"], "--restart"),
    (("analyze",), ["--port", "65534"], "--port"),       # its output port, + 2, would be past 65535
    (("decode",), ["--port", "70000"], "--port"),
    (("decode",), ["--port", "65534"], "--port"),
])
def test_reversed_ranges_and_ports_out_of_range(capsys, path, args, option):
    code, err, _ = outcome(capsys, path, args)
    refused_in_one_line(code, err, path, option)


@pytest.mark.parametrize("path, args", [
    (("analyze",), ["--vrpo-range", "80", "80"]), (("analyze",), ["--port", "65533"]),
    (("decode",), ["--port", "1"]), (("simulate", "bu"), ["--origin", "0x0101", "--outage", "1:1.5"]),
    (("simulate", "controller"), ["--restart", "2.5:50000", "--port", "65533"]),
])
def test_edges_of_the_ranges_are_accepted(capsys, path, args):
    code, err, sentinel = outcome(capsys, path, args)
    assert code == (2 if sentinel else 0) and (sentinel or "") in err and "argument" not in err, err


@pytest.mark.parametrize("argv, run", [
    (["synth", "normal", "--duration", "nan"], True), (["synth", "normal", "--duration", "inf"], True),
    (["simulate", "bu", "--delay", "inf"], False),
])
def test_values_that_ended_in_a_traceback(capsys, tmp_path, argv, run):
    code, err = in_process(capsys, [*argv, *(["--out", str(tmp_path / "x.pcap")] if run else [])], run)
    refused_in_one_line(code, err, (argv[0],), argv[-2])
    assert list(tmp_path.iterdir()) == []


def test_a_duration_of_31_years_is_refused_with_the_projected_size(capsys, tmp_path):
    out = tmp_path / "x.pcap"
    code, err = in_process(capsys, ["synth", "normal", "--duration", "1e9", "--out", str(out)])
    line = refused_in_one_line(code, err, ("synth",), "--duration")
    assert "would write about" in line and "GiB" in line and "at most" in line
    assert list(tmp_path.iterdir()) == []


def test_usage_errors_are_one_line_and_help_still_works(capsys):
    assert in_process(capsys, ["analyze", "x.pcap", "--jobs", "0"]) == (
        2, "vm110 analyze: argument --jobs: '0' is out of range: must be 1 to 256\n")
    assert in_process(capsys, ["simulate", "bu", "--loss", "101"]) == (
        2, "vm110 simulate: argument --loss: '101' is out of range: must be 0 to 100 percent\n")
    code, err = in_process(capsys, ["no-such-command"])
    assert code == 2 and err.startswith("vm110: ") and err.count("\n") == 1
    with pytest.raises(SystemExit) as info:
        cli.main(["simulate", "controller", "--help"])
    out = capsys.readouterr().out
    assert info.value.code == 0 and out.startswith("usage: vm110 simulate controller")
    assert "0 to 100 percent" in " ".join(out.split())


def test_the_analyze_options_of_the_issue(capsys):
    """10 of these 13 were accepted with exit 0 before."""
    tried = [["--vrpi-watchdog", "nan"], ["--vrpo-watchdog=-5"], ["--vrci-fail", "inf"], ["--vrco-give-up", "0"],
             ["--reuse-gap=-1"], ["--dup-window", "nan"], ["--resend", "0"], ["--burst-gap", "inf"],
             ["--vrpo-period", "0"], ["--vrpo-range", "200", "50"], ["--vrpo-range", "nan", "50"],
             ["--vrpo-data-size=-1"], ["--jobs", "0"]]
    for args in tried:
        code, err, _ = outcome(capsys, ("analyze",), args)
        refused_in_one_line(code, err, ("analyze",), args[0].split("=")[0])


@pytest.mark.parametrize("option, address, message", [
    ("--peer", "127.0.0.1:0", "not one to send to"), ("--peer", "127.0.0.1:70000", "bad address"),
    ("--listen", "127.0.0.1:-1", "bad address"), ("--source", "nohost:5825", "bad address"),
])
def test_simulate_addresses_name_their_option(option, address, message):
    """Checked before a socket is opened (here: the sockets' set-up alone, nothing is opened)."""
    args = cli.build_parser().parse_args(["simulate", "bu", option, address])
    with pytest.raises(CliError, match=f"^{option}: .*{message}"):
        simulate.udp_config(args)


@pytest.mark.parametrize("peer, said", [("8.8.8.8:5825", True), ("10.0.0.20:5825", False), ("127.0.0.1:5825", False),
                                        ("192.168.1.9:5825", False), ("239.255.42.20:5825", False)])
def test_a_public_peer_is_said(peer, said, capsys):
    """A peer outside private, loopback and multicast ranges is named on stderr (here: the
    sockets' set-up alone, nothing is opened or sent); it is not refused: plants use odd ranges."""
    cfg = simulate.udp_config(cli.build_parser().parse_args(["simulate", "bu", "--peer", peer]))
    assert cfg.dest == (peer.split(":")[0], 5825)
    err = capsys.readouterr().err
    assert (err == f"vm110 simulate: note: --peer {peer.split(':')[0]} is a public address; an EG-Link peer sits "
                   "on the local network\n") if said else err == ""


# --- the types behind the options ----------------------------------------------------------------
def test_ports_leave_room_above():
    assert port()("65535") == 65535 and port(room_above=2)("65533") == 65533
    for text in ("0", "65534", "70000", "-1", "nan", "1.5"):
        with pytest.raises(argparse.ArgumentTypeError, match="1 to 65533"):
            port(room_above=2)(text)


def test_integers_in_hex():
    assert number(0, 0xFFFF, integer=True)("0x0101") == 0x101
    assert number(0, 0xFFFF, integer=True)("010") == 10        # decimal, as before
    with pytest.raises(argparse.ArgumentTypeError):
        number(0, 0xFFFF, integer=True)("0x10000")


def test_fields():
    window = span(number(0, 60, "s"))
    assert window("1:2.5") == (1.0, 2.5) and window.range_text == "START:END, each 0 to 60 s, END after START"
    for text, message in (("2:1", "END must be after START"), ("1:1", "END must be after START"),
                          ("1", "is not START:END"), ("1:2:3", "is not START:END"), ("nan:1", "START 'nan'"),
                          ("0:61", "END '61' is out of range")):
        with pytest.raises(argparse.ArgumentTypeError, match=message):
            window(text)
    restart = fields(("AT", "PORT"), (number(0, 60, "s"), port()), required=1)
    assert restart("5") == (5.0, None) and restart("5:7000") == (5.0, 7000)
    assert restart.range_text == "AT[:PORT]: AT 0 to 60 s, PORT 1 to 65535"
    with pytest.raises(argparse.ArgumentTypeError, match="PORT '0' is out of range"):
        restart("5:0")


# --- issue 15: the issue's examples, and the gaps the audit found ---------------------------------
@pytest.mark.parametrize("path, args, option", [
    (("simulate", "bu"), ["--loss", "150"], "--loss"),
    (("simulate", "controller"), ["--period=-100"], "--period"),
    (("simulate", "controller"), ["--period", "nan"], "--period"),
    (("analyze",), ["--vrpo-range", "200", "50"], "--vrpo-range"),
    (("analyze",), ["--vrpo-period=-100"], "--vrpo-period"),
    (("analyze",), ["--burst-gap", "50"], "--burst-gap"),                    # = the default MIN: cycles join
    (("analyze",), ["--burst-gap", "30", "--vrpo-range", "25", "200"], "--burst-gap"),
    (("analyze",), ["--burst-gap", "15", "--vrpo-period", "10"], "--burst-gap"),
    (("synth",), ["--duration=-1"], "--duration"),
    (("fuzz",), ["--rate", "inf"], "--rate"),
])
def test_the_issue_s_examples_and_cross_option_checks(capsys, path, args, option):
    code, err, _ = outcome(capsys, path, args)
    refused_in_one_line(code, err, path, option)


@pytest.mark.parametrize("option", ["--period", "--vrco-timeout", "--vrpi-timeout"])
def test_simulate_times_below_the_clock_step_are_refused(capsys, option):
    """Before: `--period 0.0004` was accepted, rounded to a period of 0 µs, and the controller sent
    VRPO back to back (200,000 a second); the timeouts were 0 µs too. The clock counts µs."""
    code, err, _ = outcome(capsys, ("simulate", "controller"), [option, "0.0004"])
    assert "must be 0.001 to" in refused_in_one_line(code, err, ("simulate",), option)
    code, err, _ = outcome(capsys, ("simulate", "controller"), [option, "0.001"])
    assert code == 0 and err == "", err


@pytest.mark.parametrize("path, args", [
    (("analyze",), ["--burst-gap", "49.9"]), (("analyze",), ["--burst-gap", "5", "--vrpo-range", "10", "20"]),
    (("analyze",), ["--vrpo-period", "21"]),
])
def test_burst_gaps_below_the_vrpo_interval_are_accepted(capsys, path, args):
    code, err, sentinel = outcome(capsys, path, args)
    assert code == 2 and sentinel in err and "--burst-gap" not in err, err


@pytest.mark.parametrize("args, option, message", [
    (["--group", "10.0.0.1"], "--group", "not a multicast address"),
    (["--group", "239.255.42"], "--group", "not an IPv4 address"),
    (["--group", "ff02::1"], "--group", "not an IPv4 address"),
    (["--iface", "eth0"], "--iface", "not an IPv4 address"),
    (["--iface", "1.2.3.4.5"], "--iface", "not an IPv4 address"),
])
def test_simulate_group_and_interface_are_checked_before_a_socket_opens(args, option, message):
    parsed = cli.build_parser().parse_args(["simulate", "bu", *args])
    with pytest.raises(CliError, match=f"^{option}: .*{message}"):
        simulate.udp_config(parsed)


@pytest.mark.parametrize("args, message", [
    # They were accepted and then ran into one another: a log that went back in time (stall_end at
    # 3 s, then stopped at 2 s) and, on the virtual clock, a run that never ended.
    (["--stall", "1:3", "--stop-at", "2"], "--stop-at: 2 s is within the stall 1:3"),
    (["--stall", "1:3", "--stall", "2:4"], "--stall: 2 s is within the stall 1:3"),
    (["--stall", "1:3", "--restart", "2"], "--restart: 2 s is within the stall 1:3"),
    (["--restart", "2", "--stall", "3:4"], "--stall: 3 s is within the restart at 2 s (down for --restart-silence 1.5 s)"),
    (["--stop-at", "2", "--restart", "5"], "--restart: 5 s is within --stop-at 2 (sends nothing from then on)"),
])
def test_stalls_restarts_and_the_stop_do_not_overlap(args, message):
    parsed = cli.build_parser().parse_args(["simulate", "bu", *args])
    with pytest.raises(CliError) as info:
        simulate.life(parsed)
    assert str(info.value) == message
    touching = cli.build_parser().parse_args(["simulate", "bu", "--stall", "1:2", "--stall", "2:3", "--stop-at", "3"])
    assert simulate.life(touching)["stop_at_s"] == 3


@pytest.mark.parametrize("args, refused", [
    (["--restart", "3", "--restart", "4"], True),                      # inside the first's 1.5 s silence
    (["--restart", "4", "--restart", "3"], True),                      # in any order
    (["--restart", "3", "--restart", "3:5000"], True),
    (["--restart", "3", "--restart", "10", "--restart-silence", "8"], True),
    (["--restart", "3", "--restart", "4.5"], False),                   # back at 4.5 s, down again at once
    (["--restart", "3", "--restart", "10"], False),
])
def test_restarts_do_not_overlap(args, refused):
    parsed = cli.build_parser().parse_args(["simulate", "controller", *args])
    if refused:
        with pytest.raises(CliError, match=r"^--restart: .* is within the restart at"):
            simulate.life(parsed)
    else:
        assert [r.at_s for r in simulate.life(parsed)["restarts"]] == sorted(float(a) for a in args[1::2])
