"""Controller fuzzer: plays the base unit against a machine controller and judges what it does.

cases (what to send, reproducible from seed and case index) -> session (sockets, base-unit role,
timing) -> oracles (judging the controller) -> minimize/findings (saved, replayable results).
"""
