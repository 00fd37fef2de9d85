"""Fuzz our own tools (issue 17, part 6): mutate the bundled captures as Wireshark's fuzz testing
does (editcap -E bit flips, cuts, lying length fields) and with EG-Link-aware mutations, then run
`vm110 decode`, `vm110 analyze` (both engines) and the Lua dissector on every supported tshark,
judging each run by its exit code, its stderr and its time.

Modules: containers (pcap/pcapng record layout), mutators (file-level mutations), eglink
(mutations of the EG-Link packets inside the records), tools (what runs, where), oracles (what a
failed run is), runner (cases, failures kept under out/fuzz-self/, summary; `python -m selffuzz`).
"""
