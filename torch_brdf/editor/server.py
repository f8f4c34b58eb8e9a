"""Serve the editor through Voilà on 127.0.0.1 at a free port.

:class:`EditorServer` writes a one-cell notebook that builds :class:`~.app.EditorApp` from a
config (embedded in the cell as JSON), starts ``python -m voila`` on it in its own process
group, waits until the page answers, and stops the whole group (Voilà and its kernels) on
:meth:`stop` or when used as a context manager. The CLI (``torch-brdf editor``), the browser
tests and ``benchmarks/editor.py`` all start the editor this way.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from ..errors import TorchBRDFError

#: Debian's chromium (``apt-get install -y chromium``): Playwright's own browser download
#: cannot work on these machines, so tests and the benchmark launch the system browser
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = (
    "--no-sandbox",
    "--headless",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
)


def launch_chromium(playwright):
    """A headless system chromium through a started ``sync_playwright()`` object."""
    return playwright.chromium.launch(executable_path=CHROMIUM, args=list(CHROMIUM_ARGS))


_CELL = """\
import json
from torch_brdf.editor.app import EditorApp

app = EditorApp(json.loads({config!r}))
app.show()
"""


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def write_notebook(path: str | Path, config: dict[str, Any]) -> Path:
    """The editor's one-cell notebook (nbformat 4) at ``path``."""
    cell = _CELL.format(config=json.dumps(config))
    nb = {
        "cells": [
            {
                "cell_type": "code",
                "id": "editor",
                "metadata": {},
                "source": cell,
                "outputs": [],
                "execution_count": None,
            }
        ],
        "metadata": {"kernelspec": {"name": "python3", "display_name": "Python 3", "language": "python"}},
        "nbformat": 4,
        "nbformat_minor": 5,
    }
    path = Path(path)
    path.write_text(json.dumps(nb, indent=1))
    return path


class EditorServer:
    """A Voilà server of the editor page.

    Args:
        config: :class:`~.app.EditorApp` settings (``source`` etc.).
        port: TCP port (default: a free one).
        workdir: where the notebook and the server log go (default: a new temp dir).
        timeout: seconds to wait for the server to answer.
    """

    def __init__(
        self, config: dict[str, Any], port: int | None = None, workdir: str | Path | None = None, timeout=120.0
    ):
        self.config = dict(config)
        self.port = port or free_port()
        self._tmp = None if workdir is not None else tempfile.TemporaryDirectory(prefix="torch_brdf_editor_")
        self.workdir = Path(workdir if workdir is not None else self._tmp.name)
        self.timeout = float(timeout)
        self.proc: subprocess.Popen | None = None
        self.log_path = self.workdir / "voila.log"

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/"

    def start(self) -> EditorServer:
        """Start Voilà and wait until the page answers (TorchBRDFError if it does not)."""
        self.workdir.mkdir(parents=True, exist_ok=True)
        nb = write_notebook(self.workdir / "editor.ipynb", self.config)
        cmd = [
            sys.executable,
            "-m",
            "voila",
            str(nb),
            f"--port={self.port}",
            "--no-browser",
            "--Voila.ip=127.0.0.1",
            "--show_tracebacks=True",
        ]
        env = dict(os.environ)
        env.setdefault("PYTHONUNBUFFERED", "1")
        self._log = open(self.log_path, "w")  # closed in stop()
        self.proc = subprocess.Popen(
            cmd,
            cwd=self.workdir,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            env=env,
            start_new_session=True,
            preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None,
        )
        deadline = time.monotonic() + self.timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                self.stop()
                raise TorchBRDFError(f"voila exited with code {self.proc.returncode}; log:\n{self.log()[-2000:]}")
            try:  # listening is enough: a GET of the page would start a kernel
                with socket.create_connection(("127.0.0.1", self.port), timeout=2):
                    return self
            except OSError:
                time.sleep(0.25)
        self.stop()
        raise TorchBRDFError(f"voila did not answer at {self.url} within {self.timeout:.0f} s")

    def log(self) -> str:
        return self.log_path.read_text() if self.log_path.exists() else ""

    def _kernels(self) -> list[int]:
        """Pids of the processes Voilà started (its kernels run in sessions of their own)."""
        out = []
        for stat in Path("/proc").glob("[0-9]*/stat"):
            try:
                fields = stat.read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == self.proc.pid:  # field 4 of /proc/PID/stat: the parent pid
                out.append(int(stat.parent.name))
        return out

    def stop(self) -> None:
        """Stop Voilà and its kernels (the process group this server started and Voilà's
        children, by pid; Voilà shuts its kernels down itself on SIGTERM, this is the backstop)."""
        kernels = self._kernels() if self.proc is not None and self.proc.poll() is None else []
        if self.proc is not None and self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGTERM)
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(10)
            except ProcessLookupError:
                pass
        if self.proc is not None:
            try:  # kernels left in the group after Voilà itself exited
                os.killpg(self.proc.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
        for pid in kernels:
            try:
                os.kill(pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
        if getattr(self, "_log", None) is not None:
            self._log.close()
            self._log = None
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def __enter__(self) -> EditorServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def _die_with_parent() -> None:
    """In Voilà's process before exec (Linux): SIGTERM when the process that started it dies, so a
    killed ``torch-brdf editor`` (SIGKILL, out of memory) leaves no server behind (its own
    session keeps it out of the terminal's Ctrl-C, which :meth:`EditorServer.stop` handles)."""
    import ctypes

    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG = 1


def serve(config: dict[str, Any], port: int | None = None, echo=print) -> None:
    """``torch-brdf editor``: precompute (tqdm in the terminal) if ``config["source"]`` is a
    scene not yet in the cache, start Voilà, print the URL and serve until interrupted. A
    source that fails to load is reported here and again on the page (the server starts anyway,
    so another source can be opened from the page)."""
    from .session import load_source

    c = {**config}
    if c.get("cache_dir"):
        c["cache_dir"] = str(Path(c["cache_dir"]).resolve())
    src = Path(c["source"])
    if src.exists():
        c["source"] = str(src.resolve())
    try:
        load_source(c["source"], c.get("scene"), c.get("resolution"), c["series"], c["spp"], c["seed"], c["cache_dir"])
    except TorchBRDFError as exc:
        echo(f"warning: {exc} (the page will say so; open another source there)")
    server = EditorServer(c, port=port)

    def _interrupt(_signum, _frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _interrupt)  # a plain kill stops the server too
    try:  # from before the URL is printed: a signal right after it (a loaded machine) stops cleanly
        server.start()
        echo(f"torch_brdf editor: {server.url}  (Ctrl-C stops the server)")
        while server.proc.poll() is None:
            time.sleep(0.5)
    except KeyboardInterrupt:
        echo("torch_brdf editor: stopped")  # Ctrl-C / SIGTERM is how the server is meant to stop: exit 0
    finally:
        server.stop()
