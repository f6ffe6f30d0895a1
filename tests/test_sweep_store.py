"""Resumable sweeps: `lierk.app.store.ChunkStore` and ``lierk sweep --out DIR``.

A killed run never leaves a chunk that reads back as complete, a resumed run
gives the uninterrupted result bit for bit, and a directory holding another
run is refused."""

import json

import numpy as np
import pytest
from helpers import run_inprocess, write

from lierk.app import store as S

SCENE = """
name = "tee"
[body]
kind = "tee_handle"
[initial]
omega = [1.0, 0.05, 0.0]
[run]
solver = "RKMK4"
dt = 0.01
t1 = 0.5
"""
# 7 x 5 = 35 points in chunks of 8: 5 chunks, the last of 3.
ARGS = ["--omega-y", "-0.1:0.1:7", "--omega-z", "-0.1:0.1:5", "--chunk-size", "8", "--quiet"]
KEY = {"grid": "abc", "chunk_size": 4}


def chunk(k):
    return {"a": np.arange(4.0) + 4 * k, "b": np.full(4, k, np.int32)}


# --- the store -------------------------------------------------------------------


def test_store_round_trip_and_resume(tmp_path):
    st = S.ChunkStore.open(tmp_path / "d", key=KEY, n_chunks=3)
    assert st.done == [] and st.resumed == 0
    st.write(2, chunk(2))
    st.write(0, chunk(0))
    again = S.ChunkStore.open(tmp_path / "d", key=KEY, n_chunks=3)
    assert again.done == [0, 2] and again.resumed == 2 and not again.complete
    with pytest.raises(ValueError, match="1 of 3 chunks are missing"):
        again.read_all()
    again.write(1, chunk(1))
    out = S.ChunkStore.open(tmp_path / "d", key=KEY, n_chunks=3).read_all()
    np.testing.assert_array_equal(out["a"], np.arange(12.0))
    np.testing.assert_array_equal(out["b"], np.repeat(np.arange(3, dtype=np.int32), 4))


@pytest.mark.parametrize("damage", ["truncated", "corrupted", "deleted", "unlisted"])
def test_a_damaged_or_unlisted_chunk_is_not_complete(tmp_path, damage):
    st = S.ChunkStore.open(tmp_path, key=KEY, n_chunks=2)
    st.write(0, chunk(0))
    st.write(1, chunk(1))
    path = tmp_path / "chunk-000001.npz"
    if damage == "truncated":  # killed while writing, had it been written in place
        path.write_bytes(path.read_bytes()[:-10])
    elif damage == "corrupted":  # same size, other bytes
        b = bytearray(path.read_bytes())
        b[-5] ^= 0xFF
        path.write_bytes(bytes(b))
    elif damage == "deleted":
        path.unlink()
    else:  # killed after the chunk's rename, before the manifest listed it
        m = json.loads((tmp_path / S.MANIFEST).read_text())
        del m["chunks"]["1"]
        (tmp_path / S.MANIFEST).write_text(json.dumps(m))
    assert S.ChunkStore.open(tmp_path, key=KEY, n_chunks=2).done == [0]


def test_a_killed_write_leaves_no_chunk_and_no_temporary_file(tmp_path, monkeypatch):
    st = S.ChunkStore.open(tmp_path, key=KEY, n_chunks=2)

    def killed(file, **arrays):
        file.write(b"PK\x03\x04 half a zip")
        raise KeyboardInterrupt

    monkeypatch.setattr(S.np, "savez", killed)
    with pytest.raises(KeyboardInterrupt):
        st.write(0, chunk(0))
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == [S.MANIFEST]
    # A temporary file left by a harder kill (SIGKILL) is ignored and removed.
    (tmp_path / ".chunk-000000.npz.x1.tmp").write_bytes(b"partial")
    assert S.ChunkStore.open(tmp_path, key=KEY, n_chunks=2).done == []
    assert sorted(p.name for p in tmp_path.iterdir()) == [S.MANIFEST]


@pytest.mark.parametrize(
    "key, n, match",
    [
        ({"grid": "xyz", "chunk_size": 4}, 3, "different grid"),
        ({"grid": "abc", "chunk_size": 8}, 3, "different chunk_size"),
        (KEY, 5, "different chunk count"),
    ],
)
def test_another_run_is_refused(tmp_path, key, n, match):
    S.ChunkStore.open(tmp_path, key=KEY, n_chunks=3).write(0, chunk(0))
    with pytest.raises(ValueError, match=f"{match}.*refusing to mix"):
        S.ChunkStore.open(tmp_path, key=key, n_chunks=n)
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / S.MANIFEST).write_text("{not json")
    with pytest.raises(ValueError, match="not a lierk chunk manifest"):
        S.ChunkStore.open(tmp_path / "x", key=KEY, n_chunks=3)


def test_check_size_refuses_with_the_numbers(tmp_path, monkeypatch):
    monkeypatch.setattr(S, "available_memory", lambda: 10**9)
    S.check_size(memory=10**8, disk=10, directory=tmp_path / "new")
    with pytest.raises(ValueError, match=r"needs about 7.2 GB of memory and 1 GB is available"):
        S.check_size(memory=72 * 10**8, disk=10, directory=tmp_path, what="x")
    with pytest.raises(ValueError, match=r"writes about 1e\+03 TB and .* free"):
        S.check_size(memory=1, disk=10**15, directory=tmp_path)


# --- the command line ------------------------------------------------------------


def test_sweep_resumes_bit_for_bit_and_refuses_another_run(tmp_path, capsys, monkeypatch):
    scene = write(tmp_path, SCENE)
    code, out, err = run_inprocess(["sweep", scene, "--out", tmp_path / "whole", *ARGS], capsys)
    assert code == 0, err
    whole = np.load(tmp_path / "whole" / "tee_sweep.npz")

    # Killed after two chunks were written.
    real_write, calls = S.ChunkStore.write, []

    def write_then_die(self, k, arrays):
        if len(calls) == 2:
            raise KeyboardInterrupt
        calls.append(k)
        real_write(self, k, arrays)

    monkeypatch.setattr(S.ChunkStore, "write", write_then_die)
    code, out, err = run_inprocess(["sweep", scene, "--out", tmp_path / "cut", *ARGS], capsys)
    assert code == 130 and not (tmp_path / "cut" / "tee_sweep.npz").exists()
    monkeypatch.undo()

    # Another run in the unfinished run's directory: one line, nothing mixed in.
    code, out, err = run_inprocess(["sweep", scene, "--out", tmp_path / "cut", *ARGS, "--t1", "0.6"], capsys)
    assert code == 2 and err.count("\n") == 1 and "different" in err and "refusing to mix" in err
    m = json.loads((tmp_path / "cut" / "tee_sweep.chunks" / S.MANIFEST).read_text())
    assert m["key"]["t1"] == 0.5 and sorted(m["chunks"]) == ["0", "1"]

    code, out, err = run_inprocess(["sweep", scene, "--out", tmp_path / "cut", *ARGS], capsys)
    assert code == 0 and err == "lierk sweep: resuming: 2 of 5 chunks already done\n"
    resumed = np.load(tmp_path / "cut" / "tee_sweep.npz")
    assert sorted(resumed.files) == sorted(whole.files)
    for k in whole.files:
        np.testing.assert_array_equal(resumed[k], whole[k], err_msg=k)
        assert resumed[k].dtype == whole[k].dtype
    # Finished: the chunks are in the .npz, and their directory is gone.
    assert sorted(p.name for p in (tmp_path / "cut").iterdir()) == ["tee_sweep.npz", "tee_sweep.png"]


@pytest.mark.parametrize(
    "extra, status, message",
    [
        (["--chunk-size", "0"], 2, "--chunk-size must be a positive integer, got '0'"),
        (["--chunk-size", "-3"], 2, "--chunk-size must be a positive integer"),
        (["--num-processes", "2", "--process-id", "5", "--coordinator-address", "localhost:1"], 2, "process_id"),
    ],
)
def test_sweep_bad_settings_are_one_line(tmp_path, capsys, extra, status, message):
    code, out, err = run_inprocess(["sweep", write(tmp_path, SCENE), "--out", tmp_path / "o", *ARGS, *extra], capsys)
    assert code == status and err.count("\n") == 1 and message in err, err
    assert "Traceback" not in err


def test_simulate_refuses_a_run_that_cannot_fit(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(S, "available_memory", lambda: 10**4)
    code, out, err = run_inprocess(["simulate", write(tmp_path, SCENE), "--out", tmp_path / "o", "--quiet"], capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert "simulating 51 saved points needs about" in err and "10 KB is available" in err
