"""registration.io on its own: atomic writes survive a SIGKILL at any moment (a reader sees the
old file or the new one, never a part), temporary files are recognisable, and the JSON/NPZ/image
writers round trip."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from registration.io import (
    atomic_path,
    read_image,
    temp_target,
    write_bytes_atomic,
    write_image_atomic,
    write_json_atomic,
    write_npz_atomic,
)

REPO = Path(__file__).resolve().parents[2]

# Two payloads the child alternates between; every byte says which one it belongs to, so a file
# mixing them, or cut short, is recognised.
PAYLOAD_MB = 24

CHILD = r"""
import sys
from registration.io import write_bytes_atomic
path, size = sys.argv[1], int(sys.argv[2])
payloads = [b"A" * size, b"B" * size]
write_bytes_atomic(path, payloads[0])
print("ready", flush=True)
i = 1
while True:
    write_bytes_atomic(path, payloads[i % 2])
    i += 1
"""


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs POSIX signals")
def test_atomic_write_survives_sigkill_at_any_moment(tmp_path):
    """A process rewriting a 24 MB file in a loop is killed at 12 seeded moments; each time the
    file is whole (one of the two payloads, full length), and the only leftovers are temporary
    files named as result folders expect (``.NAME.*.tmp``, ignored and cleaned by them)."""
    size = PAYLOAD_MB << 20
    target = tmp_path / "data.bin"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    delays = np.random.default_rng(16).uniform(0.0, 0.25, 12)
    for delay in delays:
        child = subprocess.Popen(
            [sys.executable, "-c", CHILD, str(target), str(size)],
            env=env,
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            assert child.stdout.readline().strip() == "ready"
            time.sleep(float(delay))
        finally:
            child.send_signal(signal.SIGKILL)
            child.wait()
            child.stdout.close()
        data = target.read_bytes()
        assert len(data) == size, f"killed after {delay:.3f} s: {len(data)} of {size} bytes"
        assert data[:1] in (b"A", b"B") and data.count(data[:1]) == size, (
            f"killed after {delay:.3f} s: the file mixes the two payloads"
        )
    for p in tmp_path.iterdir():
        assert p == target or temp_target(p.name) == target.name, p.name
    # The next writer replaces the file as usual.
    write_bytes_atomic(target, b"done")
    assert target.read_bytes() == b"done"


def test_writers_round_trip_and_leave_no_temporary(tmp_path):
    obj = {"a": np.float32(1.5), "b": np.arange(3), "c": tmp_path, "d": [np.int64(7)]}
    write_json_atomic(tmp_path / "x.json", obj)
    assert json.loads((tmp_path / "x.json").read_text()) == {
        "a": 1.5, "b": [0, 1, 2], "c": str(tmp_path), "d": [7],
    }  # fmt: skip
    arrays = {"u": np.arange(12.0).reshape(3, 4), "v": np.array([True, False])}
    write_npz_atomic(tmp_path / "y.npz", **arrays)
    with np.load(tmp_path / "y.npz") as z:
        for name, value in arrays.items():
            np.testing.assert_array_equal(z[name], value)
    image = np.random.default_rng(1).integers(0, 256, (20, 30, 3), dtype=np.uint8)
    write_image_atomic(tmp_path / "sub" / "z.png", image)  # creates the folder
    np.testing.assert_array_equal(read_image(tmp_path / "sub" / "z.png"), image)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sub", "x.json", "y.npz"]
    # Readable by others (mkstemp's default 0600 would hide results).
    assert (tmp_path / "x.json").stat().st_mode & 0o044 == 0o044


def test_failed_write_keeps_the_old_file(tmp_path):
    target = tmp_path / "keep.json"
    write_json_atomic(target, {"v": 1})
    with pytest.raises(TypeError):
        write_json_atomic(target, {"v": object()})
    assert json.loads(target.read_text()) == {"v": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["keep.json"]


def test_written_files_get_the_permissions_the_umask_gives(tmp_path):
    """Every writer goes through ``atomic_path``: a new file is 0666 minus the umask, as an
    ordinary ``open(..., "w")`` gives (mkstemp alone would give 0600), also under umask 027."""
    code = (
        "import os, sys; os.umask(0o027)\n"
        "from registration.io import write_bytes_atomic, atomic_path\n"
        "write_bytes_atomic(sys.argv[1] + '/a.bin', b'x')\n"
        "with atomic_path(sys.argv[1] + '/b.tif') as tmp:\n"
        "    assert tmp.name.startswith('.b.tif.') and tmp.name.endswith('.tmp')\n"
        "    tmp.write_bytes(b'y')\n"
        "with atomic_path(sys.argv[1] + '/c.mp4', keep_suffix=True) as tmp:\n"
        "    assert tmp.name.endswith('.tmp.mp4')\n"
        "    tmp.write_bytes(b'z')\n"
    )
    env = dict(os.environ, PYTHONPATH=str(REPO))
    subprocess.run([sys.executable, "-c", code, str(tmp_path)], env=env, check=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin", "b.tif", "c.mp4"]
    for name in ("a.bin", "b.tif", "c.mp4"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o640, name
    write_bytes_atomic(tmp_path / "c.bin", b"z")  # this process's umask
    mask = os.umask(0)
    os.umask(mask)
    assert (tmp_path / "c.bin").stat().st_mode & 0o777 == 0o666 & ~mask


def test_atomic_path_removes_its_file_when_the_writer_fails(tmp_path):
    (tmp_path / "v.mp4").write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic_path(tmp_path / "v.mp4") as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError("encoder died")
    assert [p.name for p in tmp_path.iterdir()] == ["v.mp4"]
    assert (tmp_path / "v.mp4").read_bytes() == b"old"
