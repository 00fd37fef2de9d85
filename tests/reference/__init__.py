"""An independent reference for the analysis rules (docs/rules.md) and a random EG-Link traffic
generator. Nothing here imports `vm110`: the point is a second implementation that shares no code
(and as few assumptions as possible) with the engines it checks."""
