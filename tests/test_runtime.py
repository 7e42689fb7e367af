"""What a long-running script needs besides the models (gpg.runtime): JSON and bytes written
atomically, the float64 policy for a whole function, Ctrl-C at safe points."""

import json
import os
import signal
import stat
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg import runtime


def test_write_json_writes_arrays_scalars_and_paths(tmp_path):
    path = tmp_path / "r.json"
    obj = {"a": np.arange(3.0), "b": jnp.ones((2, 2)), "c": np.float32(0.5), "d": Path("x/y")}
    runtime.write_json(path, obj)
    assert json.loads(path.read_text()) == {
        "a": [0.0, 1.0, 2.0],
        "b": [[1.0, 1.0], [1.0, 1.0]],
        "c": 0.5,
        "d": "x/y",
    }
    assert not [p for p in tmp_path.iterdir() if p.name != "r.json"]  # no temporary left


def test_write_json_refuses_what_json_cannot_hold_and_keeps_the_old_file(tmp_path):
    path = tmp_path / "r.json"
    runtime.write_json(path, {"ok": 1})
    with pytest.raises(TypeError, match="not JSON serialisable: object"):
        runtime.write_json(path, {"bad": object()})
    assert json.loads(path.read_text()) == {"ok": 1}


def test_atomic_write_gives_the_permissions_of_a_plain_open(tmp_path):
    mask = os.umask(0)
    os.umask(mask)
    out = runtime.atomic_write(tmp_path / "b.bin", b"\x00\x01")
    assert out.read_bytes() == b"\x00\x01"
    assert stat.S_IMODE(out.stat().st_mode) == 0o666 & ~mask


def test_float64_widens_a_float32_program():
    @runtime.float64
    def f(x):
        return x * 2

    with jax.enable_x64(False):
        y = f(jnp.ones(3, jnp.float32))
    assert y.dtype == jnp.float64


def test_a_ctrl_c_inside_the_block_is_raised_at_the_next_safe_point():
    # What the process started with (a shell's background job starts with SIGINT ignored).
    before = signal.getsignal(signal.SIGINT)
    runtime.check_interrupt()  # outside the block: nothing
    with pytest.raises(KeyboardInterrupt), runtime.deferred_interrupt():
        os.kill(os.getpid(), signal.SIGINT)
        reached = True  # the signal only set the flag
        runtime.check_interrupt()
    assert reached
    assert signal.getsignal(signal.SIGINT) is before
