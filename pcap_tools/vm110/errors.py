"""Exit codes shared by every `vm110` subcommand, and the one exception they turn into code 2."""
from __future__ import annotations

EXIT_OK = 0
EXIT_FINDINGS = 1       # the job ran and found what it was asked to flag
EXIT_USAGE = 2          # usage error or unreadable input
EXIT_INTERRUPTED = 130


class CliError(Exception):
    """A problem the user can fix; printed as one line, exit code 2."""
