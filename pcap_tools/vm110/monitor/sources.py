"""Where the capture bytes come from: dumpcap on an interface, a file followed as it grows, or
standard input. `read(timeout)` returns the next bytes, b"" when none came within `timeout`
seconds, None at the end of the input."""
from __future__ import annotations

import glob
import os
import re
import select
import shutil
import stat
import subprocess
import tempfile
import time
from typing import Optional

from ..capture.reader import PCAPNG_SHB
from ..errors import CliError

READ_SIZE = 1 << 16            # a pipe's worth
FILE_READ_SIZE = 1 << 20       # a file: larger batches for the analysis
PACED_READ_SIZE = 1 << 12      # --realtime: read little ahead of the pace
DUMPCAP_HINT = ("capturing needs rights: run as root, or let dumpcap capture (Debian: dpkg-reconfigure "
                "wireshark-common, then join the wireshark group; elsewhere: "
                "setcap cap_net_raw,cap_net_admin=ep dumpcap)")
# dumpcap, the child of a shell that stops it when the shell ends or is asked to (SIGTERM), giving
# dumpcap's exit status as its own. The kernel signals the shell when the monitor dies however it
# dies (prctl PR_SET_PDEATHSIG, set by setpriv): set on dumpcap itself it would not hold, the exec
# of a program with capabilities or setuid (dumpcap for a user of the wireshark group) clears it.
# Should the monitor die before setpriv set it, dumpcap's first write (its pcapng header) to the
# pipe no one reads ends dumpcap.
# A file of dumpcap's ring buffer (-b filesize:/duration:/files:): PREFIX_NNNNN_YYYYMMDDhhmmss.EXT
RING = re.compile(r"^(?P<head>.*_)(?P<n>\d{5,})_\d{14}(?P<ext>\.[^./]*)?$")
TIED = ('trap \'kill -TERM "$c" 2>/dev/null\' HUP INT TERM; "$@" & c=$!; '
        'while :; do wait "$c"; s=$?; kill -0 "$c" 2>/dev/null || exit "$s"; done')


class Source:
    name = ""

    def read(self, timeout: float) -> Optional[bytes]:
        raise NotImplementedError

    def close(self) -> None:
        """Stop reading (the process or file of the source is let go)."""

    def rest(self, timeout: float) -> bytes:
        """What the source still gives, within `timeout` seconds, when the run stops before its
        input ended: nothing, but for dumpcap."""
        return b""

    def failure(self) -> Optional[str]:
        """Why the input ended, when it was not the end of the data."""
        return None

    def quiet(self) -> Optional[float]:
        """Seconds since a followed file last grew (None: not a followed file)."""
        return None


class PipeSource(Source):
    """A pipe or standard input (file descriptor `fd`, not closed here)."""

    def __init__(self, fd: int, name: str, size: int = READ_SIZE) -> None:
        self.fd, self.name, self.size = fd, name, size

    def read(self, timeout: float) -> Optional[bytes]:
        try:
            ready, _, _ = select.select([self.fd], [], [], timeout)
        except (OSError, ValueError) as exc:
            raise CliError(f"cannot read {self.name}: {exc}") from None
        if not ready:
            return b""
        try:
            data = os.read(self.fd, self.size)
        except OSError as exc:
            raise CliError(f"cannot read {self.name}: {exc.strerror or exc}") from None
        return data or None


class FollowFile(Source):
    """A capture file read as it grows (tail -f); the input ends when it has not grown for `idle`
    seconds (None: never, until interrupted), or when its path leads elsewhere: another file renamed
    over it, or this one cut shorter than what was read (what comes then is another capture, not the
    rest of this one). A file removed is still read through what was opened: its writer may go on.
    A pcapng file of dumpcap's ring buffer goes on in the ring's next file once that exists (dumpcap
    makes it after closing this one): read on there, as one stream of pcapng sections."""

    def __init__(self, path: str, idle: Optional[float], size: int = FILE_READ_SIZE) -> None:
        self.name, self.idle, self.size = path, idle, size
        try:
            self.file = open(path, "rb")   # noqa: SIM115 -- the source owns it; close()
        except OSError as exc:
            raise CliError(f"cannot read {path}: {exc.strerror}") from None
        st = os.fstat(self.file.fileno())
        self.identity = (st.st_dev, st.st_ino) if stat.S_ISREG(st.st_mode) else None   # (a FIFO has no size)
        self.grew = time.monotonic()
        self.at_end = False                # the last read found nothing new
        self.gone: Optional[str] = None
        self.ring = self.identity is not None and RING.match(os.path.basename(path)) is not None \
            and int.from_bytes(os.pread(self.file.fileno(), 4, 0), "little") == PCAPNG_SHB  # (pcapng)

    def read(self, timeout: float) -> Optional[bytes]:
        try:
            data = self.file.read(self.size)
        except OSError as exc:
            raise CliError(f"cannot read {self.name}: {exc.strerror or exc}") from None
        self.at_end = not data
        if data:
            self.grew = time.monotonic()
            return data
        if self.ring and self._next_in_ring():
            return b""
        self.gone = self._gone()
        if self.gone is not None or (self.idle is not None and time.monotonic() - self.grew >= self.idle):
            return None
        time.sleep(timeout if self.idle is None else min(timeout, max(0.0, self.idle)))
        return b""

    def _next_in_ring(self) -> bool:
        """Whether the ring's next file is now the one read (this one read to its end)."""
        m = RING.match(os.path.basename(self.name))
        assert m is not None
        folder = os.path.dirname(self.name)
        later = sorted(glob.glob(os.path.join(glob.escape(folder), glob.escape(f"{m['head']}{int(m['n']) + 1:05d}_")
                                              + "[0-9]" * 14 + glob.escape(m["ext"] or ""))))
        if not later:
            return False
        if self.file.read(1):                   # (this one was still written meanwhile: to its end first)
            self.file.seek(-1, os.SEEK_CUR)
            return False
        try:
            nxt = open(later[0], "rb")          # noqa: SIM115 -- the source owns it; close()
        except OSError:                         # (removed already by -b files:N: read on where we are)
            return False
        self.file.close()
        self.file, self.name = nxt, later[0]
        st = os.fstat(nxt.fileno())
        self.identity, self.grew = (st.st_dev, st.st_ino), time.monotonic()
        return True

    def _gone(self) -> Optional[str]:
        """Why the path no longer leads to the rest of what was read (None: it still may)."""
        if self.identity is None:
            return None
        try:
            st = os.stat(self.name)
        except OSError:                 # removed (or out of reach): what was opened may still grow
            return None
        if (st.st_dev, st.st_ino) != self.identity:
            return f"{self.name} was replaced by another file while followed"
        if st.st_size < self.file.tell():
            return f"{self.name} was cut shorter ({st.st_size} bytes) than what was read ({self.file.tell()})"
        return None

    def failure(self) -> Optional[str]:
        return None if self.gone is None else f"{self.gone}: the report is of what was read before"

    def quiet(self) -> Optional[float]:
        # (at its end only: a monitor busy with what it read long ago has not seen the file since)
        return time.monotonic() - self.grew if self.at_end else 0.0

    def close(self) -> None:
        self.file.close()


def capture_filter(ports: tuple[int, ...], tagged: bool) -> str:
    """dumpcap's filter: UDP to or from the EG-Link ports, and every IP fragment but an IPv4 first
    one (which shows its ports): a VRPO fragmented by a small MTU is reassembled by the reader, as
    Wireshark and `analyze` do, and the fragments after its first show no port (the IPv6 ones not
    even UDP, behind their fragment header). The same behind one VLAN tag or two (802.1Q, QinQ):
    on a trunk a tag the kernel left in the frame (a frame sent, a second tag) moves every offset
    the plain filter reads, and libpcap reads past a tag only after `vlan`, which it applies to
    the rest of the expression (hence nested, not `F or (vlan and F) or (vlan and vlan and F)`).
    `tagged` False: the plain filter, for a link type without VLAN tags, where libpcap refuses
    `vlan` (`-i any`, a tun interface)."""
    plain = (f"(udp and ({' or '.join(f'port {p}' for p in ports)})) or (ip[6:2] & 0x1fff != 0)"
             " or (ip6 and ip6[6] == 44)")
    return f"{plain} or (vlan and ({plain} or (vlan and ({plain}))))" if tagged else plain


def ethernet(iface: str) -> bool:
    """Whether `iface` is an Ethernet interface (ARPHRD_ETHER), whose frames may carry VLAN tags."""
    if "/" in iface:
        return False
    try:
        with open(f"/sys/class/net/{iface}/type", encoding="ascii") as f:
            return f.read().strip() == "1"
    except (OSError, ValueError):     # (`any`, an interface number, not Linux: no tags looked for)
        return False


class Dumpcap(Source):
    """Wireshark's capture engine on interface `iface`, filtered to the EG-Link ports and IP
    fragments (`capture_filter`), its pcapng read from a pipe as it arrives."""

    def __init__(self, iface: str, ports: tuple[int, ...]) -> None:
        self.name = iface
        exe = shutil.which("dumpcap")
        if exe is None:
            raise CliError("dumpcap not found: install Wireshark's capture engine (Debian: tshark or wireshark-common)")
        flt = capture_filter(ports, ethernet(iface))
        self.errors = tempfile.TemporaryFile()   # noqa: SIM115 -- dumpcap's stderr while it runs; close()
        setpriv = shutil.which("setpriv")
        tie = [setpriv, "--pdeathsig", "TERM", "--"] if setpriv else []
        # -q: no packet counts on stderr; -w -: pcapng to the pipe, a block per packet as it comes.
        self.proc = subprocess.Popen([*tie, "/bin/sh", "-c", TIED, "dumpcap", exe, "-q", "-i", iface, "-f", flt,
                                      "-w", "-"], stdout=subprocess.PIPE, stderr=self.errors, stdin=subprocess.DEVNULL)
        assert self.proc.stdout is not None
        self.pipe = PipeSource(self.proc.stdout.fileno(), f"dumpcap on {iface}")
        self.got_data = False

    def read(self, timeout: float) -> Optional[bytes]:
        data = self.pipe.read(timeout)
        if data:
            self.got_data = True
        return data

    def failure(self) -> Optional[str]:
        try:
            code = self.proc.wait(timeout=2)
        except subprocess.TimeoutExpired:
            return None
        self.errors.seek(0)
        text = self.errors.read().decode("utf-8", "replace")
        lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
        said = [ln for ln in lines if ln.startswith("dumpcap:")]
        if code == 0 and not said:
            return None
        message = said[0] if said else (lines[-1] if lines else f"dumpcap exited with status {code}")
        after = lines[lines.index(message) + 1] if message in lines and lines.index(message) + 1 < len(lines) else ""
        if after.startswith("("):
            message = f"{message} {after}"
        if "permission" in message.lower():
            message = f"{message}; {DUMPCAP_HINT}"
        return f"{message} (interface {self.name})"

    def rest(self, timeout: float) -> bytes:
        """dumpcap stopped (the shell passes SIGTERM on), and what it writes until it ends: the last
        packets and its statistics of each interface, which say what it dropped."""
        if self.proc.poll() is None:
            self.proc.terminate()
        out, deadline = [], time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            data = self.pipe.read(left)
            if not data:                  # (None: dumpcap ended; b"": the time is up)
                break
            out.append(data)
        return b"".join(out)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self.errors.close()
