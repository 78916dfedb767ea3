"""The store's claim (``.lock``) is opened without following a link and
taken only when it is a regular file of its own: a symbolic link (to a file
outside the store, to a device, dangling), a hard link to another file, a
directory or a FIFO is refused with one error naming ``store``, and no file
outside the store is truncated or written."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

pytest.importorskip("fastapi")

from hybridmpm.errors import InvalidInputError  # noqa: E402
from hybridmpm.service.store import SessionStore  # noqa: E402

SECRET = b"a file outside the store, never to be truncated\n"


def _refused(store_dir):
    store = SessionStore(str(store_dir)).open()
    with pytest.raises(InvalidInputError) as e:
        store.claim()
    assert e.value.field == "store" and str(e.value).startswith("store:") and ".lock" in str(e.value), str(e.value)
    assert "\n" not in str(e.value)
    assert store._lock_fd is None
    return str(e.value)


def test_a_lock_that_is_not_a_regular_file_of_its_own_is_refused(tmp_path):
    outside = tmp_path / "precious.txt"
    outside.write_bytes(SECRET)
    cases = {
        "symlink": lambda p: os.symlink(outside, p),
        "symlink to a device": lambda p: os.symlink("/dev/null", p),
        "dangling symlink": lambda p: os.symlink(tmp_path / "nowhere", p),
        "hard link": lambda p: os.link(outside, p),
        "directory": lambda p: os.mkdir(p),
        "fifo": lambda p: os.mkfifo(p),
    }
    for name, make in cases.items():
        d = tmp_path / name.replace(" ", "_")
        d.mkdir()
        make(d / ".lock")
        msg = _refused(d)
        assert outside.read_bytes() == SECRET, name
        assert not (tmp_path / "nowhere").exists(), name
        print(f"{name}: {msg}")
    # a regular .lock (a previous server's) is taken over: its content is the holder's pid now
    d = tmp_path / "plain"
    d.mkdir()
    (d / ".lock").write_bytes(b"12345")
    store = SessionStore(str(d)).open()
    store.claim()
    try:
        assert (d / ".lock").read_bytes().decode().startswith(str(os.getpid()))
    finally:
        store.release()


def test_serve_on_a_store_whose_lock_is_a_link_exits_with_one_line_naming_store(tmp_path):
    outside = tmp_path / "precious.txt"
    outside.write_bytes(SECRET)
    store = tmp_path / "store"
    store.mkdir()
    os.symlink(outside, store / ".lock")
    r = subprocess.run(
        [sys.executable, "-m", "hybridmpm", "serve", "--host", "127.0.0.1", "--port", "0", "--store", str(store)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode != 0
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert "Traceback" not in r.stderr and any("store" in line and ".lock" in line for line in lines), r.stderr[-2000:]
    assert outside.read_bytes() == SECRET
