"""`vm110 monitor`: the analysis of `vm110 analyze` on a live link, with a dashboard, alarms and
evidence (docs/monitor.md).

- `intake`: datagrams judged into the analysis exactly as the fast engine judges a file's;
- `live`: what the dashboard shows and the alarms that cannot wait for the end (watchdog while
  the link is silent, lost packets, failed commands, illegal packets);
- `evidence`: a bounded ring of recent frames, written around each alarm as pcapng;
- `dashboard`: the terminal view; `sources`: dumpcap, a followed file, standard input;
- `outlet`: standard output written without waiting for its reader;
- `session`: the loop that ties them together and ends with the report of `analyze`.
"""
