"""vm110.numbers: the validated number type of command-line options."""
from __future__ import annotations

import argparse

import pytest

from vm110.numbers import number

RATE = number(0, 10000, "packets/s", allow_zero=False)
COUNT = number(1, 1000, integer=True)


@pytest.mark.parametrize("text", ["nan", "NaN", "inf", "-inf", "infinity", "1e999", "-1", "0", "0.0", "-0",
                                  "10000.5", "1e18", "", "abc", "0x10", "\uff11", "\u0661\u0662"])
def test_refused(text):
    with pytest.raises(argparse.ArgumentTypeError, match=r"above 0 and at most 10000 packets/s"):
        RATE(text)


@pytest.mark.parametrize("text, value", [("1", 1.0), ("0.25", 0.25), ("10000", 10000.0), ("1e2", 100.0)])
def test_accepted(text, value):
    assert RATE(text) == value


def test_integers():
    assert COUNT("7") == 7 and isinstance(COUNT("7"), int)
    for text in ("1.5", "1e3", "0", "1001", "nan", "9" * 5000, "\uff17", "\u0967"):
        with pytest.raises(argparse.ArgumentTypeError, match="1 to 1000"):
            COUNT(text)


def test_zero_allowed_by_default():
    assert number(0, 5, "s")("0") == 0.0


def test_range_texts():
    assert number(0, 2592000, "s", allow_zero=False).range_text == "above 0 and at most 2592000 s"
    assert number(-10, 10, "mm", allow_zero=False).range_text == "-10 to 10 mm, not 0"
    assert number(0.01, 1e4).range_text == "0.01 to 10000"
    assert number(0, 2**64 - 1, integer=True).range_text == "0 to 18446744073709551615"
    with pytest.raises(argparse.ArgumentTypeError):
        number(-10, 10, allow_zero=False)("0")


def test_message_names_the_option_through_argparse(capsys):
    parser = argparse.ArgumentParser(prog="t")
    parser.add_argument("--rate", type=RATE)
    with pytest.raises(SystemExit) as info:
        parser.parse_args(["--rate", "nan"])
    assert info.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert "--rate" in last and "'nan'" in last and "packets/s" in last


def test_a_bad_range_is_a_programming_error():
    for low, high in ((1, 0), (0, float("inf")), (float("nan"), 1)):
        with pytest.raises(ValueError):
            number(low, high)
