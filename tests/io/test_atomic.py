"""Atomic writes: a writer killed mid-write leaves its temporary file, the next write of the
same target removes it; temporaries of live writers are left alone."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from torch_brdf.io.arrays import load_arrays, save_arrays
from torch_brdf.io.atomic import remove_stale_temporaries, replacing

# a writer that stops in the middle of its write and waits to be killed
_WRITER = """
import sys, time
from torch_brdf.io.atomic import replacing
with replacing(sys.argv[1]) as tmp, open(tmp, "wb") as f:
    f.write(b"partial" * 1000)
    f.flush()
    print(tmp, flush=True)
    time.sleep(120)
"""


def _start_writer(target: Path) -> tuple[subprocess.Popen, Path]:
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(target)], stdout=subprocess.PIPE, text=True, env=env)
    line = proc.stdout.readline().strip()
    assert line, "writer did not start"
    return proc, Path(line)


def _temporaries(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs SIGKILL")
def test_sigkilled_writer_leaves_a_temporary_that_the_next_write_removes(tmp_path):
    target = tmp_path / "tensors.npz"
    proc, tmp = _start_writer(target)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    proc.stdout.close()
    assert tmp.exists() and not target.exists()  # the kill left the temporary behind
    assert f".{proc.pid}." in tmp.name  # it names its writer
    save_arrays(target, {"a": np.arange(3)}, kind="test")
    assert _temporaries(tmp_path) == []
    assert load_arrays(target, kind="test")[0]["a"].tolist() == [0, 1, 2]


def test_temporaries_of_live_writers_and_other_targets_stay(tmp_path):
    target = tmp_path / "image.exr"
    proc, tmp = _start_writer(target)
    try:
        other = tmp_path / f".other.exr.{proc.pid + 10**7}.0123456789ab.tmp"  # another target's
        other.write_bytes(b"x")
        with replacing(target) as mine:
            Path(mine).write_bytes(b"done")
        assert target.read_bytes() == b"done"
        assert tmp.exists() and other.exists()
    finally:
        proc.kill()
        proc.wait(timeout=30)
        proc.stdout.close()
    assert remove_stale_temporaries(target) == [str(tmp)]


def test_old_style_temporaries_are_removed_when_they_predate_the_process(tmp_path):
    target = tmp_path / "ckpt.npz"
    old = tmp_path / ".ckpt.npz.0123456789ab.tmp"
    old.write_bytes(b"x")
    past = old.stat().st_mtime - 3600  # an hour before it was written
    os.utime(old, (past, past))
    assert remove_stale_temporaries(target) == [str(old)]


def test_a_failed_write_removes_its_own_temporary(tmp_path):
    target = tmp_path / "out.png"
    with pytest.raises(OSError), replacing(target) as tmp:
        Path(tmp).write_bytes(b"half")
        raise OSError(28, "No space left on device")
    assert _temporaries(tmp_path) == [] and not target.exists()


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc (a folder that refuses files)")
def test_a_folder_that_refuses_files_raises_the_os_error_naming_the_target():
    # OpenEXR raised a bare RuntimeError there, which the CLI reported as an internal error
    from torch_brdf.io import write_exr

    with pytest.raises(OSError) as info:
        write_exr("/proc/refused.exr", np.zeros((2, 2, 3), np.float32))
    assert info.value.errno is not None and info.value.filename == "/proc/refused.exr"
