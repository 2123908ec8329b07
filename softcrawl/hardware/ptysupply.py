"""The simulated BK 9129B served on a pseudo-terminal, for end-to-end tests and dry runs of the
real-rig path: ``softcrawl deploy --rig rig.toml`` talks to it through pyvisa, pyvisa-py and
pyserial exactly as to the supply's USB-serial port, and the fake's state (outputs, set
voltages, remote mode, the full transcript) stays readable here after that process has
ended, however it ended.

Example::

    with PtySupply() as fake:
        # rig.toml: [supply] address = fake.address (e.g. "ASRL/dev/pts/7::INSTR")
        ...  # run `softcrawl deploy --rig rig.toml ...` in a subprocess, stop it
        assert not fake.supply.on and not fake.supply.set_v.any()

POSIX only (:func:`os.openpty`). Each line the client sends (``\\n`` terminated) is one SCPI
command: a query (ending in ``?``) is answered with one line, a setting is not answered (as
the 9129B does). A command outside the exact exchange of :class:`FakeBK9129B` is recorded in
``errors`` and not answered; so is every command while the fake's fault injection
(``fail_from``) says the port is gone.
"""

from __future__ import annotations

import os
import select
import threading
import tty

from softcrawl.hardware.simrig import FakeBK9129B, SCPIProtocolError


class PtySupply:
    """A :class:`FakeBK9129B` (``supply``, no simulated clock) answering on a pseudo-terminal.

    Attributes:
        address: the VISA resource name of the terminal, ``"ASRL/dev/pts/N::INSTR"``.
        supply: the fake instrument; ``errors``: protocol violations seen, in order.
    """

    def __init__(self, supply: FakeBK9129B | None = None) -> None:
        self.supply = supply or FakeBK9129B(None)
        self.errors: list[str] = []
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line editing: bytes pass as sent
        self.address = f"ASRL{os.ttyname(self._slave)}::INSTR"
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True, name="softcrawl-pty-supply")
        self._thread.start()

    def _serve(self) -> None:
        buf = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], 0.05)
            if not ready:
                continue
            try:
                chunk = os.read(self._master, 4096)
            except OSError:  # the terminal is gone
                return
            buf += chunk
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                self._answer(line.decode("ascii", "replace").strip())

    def _answer(self, cmd: str) -> None:
        if not cmd:
            return
        try:
            if cmd.endswith("?"):
                os.write(self._master, (self.supply.query(cmd) + "\n").encode("ascii"))
            else:
                self.supply.write(cmd)
        except SCPIProtocolError as exc:
            self.errors.append(str(exc))
        except ConnectionError:  # fault injection: the port is gone, nothing answers
            pass

    def close(self) -> None:
        """Stop serving and close the terminal."""
        self._stop.set()
        self._thread.join(timeout=5)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> PtySupply:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
