"""Capture files: reading (reader.py) and writing (writer.py) pcap and pcapng."""
