"""batch.run_sharded over two JAX processes on this machine (``batch.start_distributed``: a
local coordinator, gloo collectives on CPU) against the same items in one process."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap

import numpy as np

_RUN = textwrap.dedent(
    """
    import json, sys
    import jax
    n_processes, process_id, port = (int(a) for a in sys.argv[1:4])
    if n_processes > 1:
        from cpf_jax.batch import start_distributed
        start_distributed(f"127.0.0.1:{port}", n_processes, process_id)
    import jax.numpy as jnp
    from cpf_jax.batch import run_sharded
    from cpf_jax.colour import ColourConfig, build_colour_filter, default_colour_params
    from cpf_jax.filter import track_boxes
    from cpf_jax.synthetic import make_sequence
    from cpf_jax.types import Frame

    seq = make_sequence("walk_across_fast", seed=2, n_frames=8)
    frames = Frame(jnp.asarray(seq.colour), jnp.asarray(seq.depth))
    config = ColourConfig(n_particles=64).with_window(seq.boxes[0, 2:], seq.colour.shape[1:3])
    filt, params = build_colour_filter(config), default_colour_params()

    def one(key, frames, box):
        return track_boxes(filt, params, key, frames, box)

    keys = jax.random.split(jax.random.PRNGKey(3), 3)  # odd: one item of padding
    boxes, lost = run_sharded(one, keys, frames, jnp.asarray(seq.boxes[0]))
    print(json.dumps({
        "processes": jax.process_count(),
        "devices": len(jax.devices()),
        "boxes": jnp.asarray(boxes).tolist(),
        "lost": jnp.asarray(lost).tolist(),
    }))
    """
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start(n: int, i: int, port: int) -> subprocess.Popen:
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    return subprocess.Popen(
        [sys.executable, "-c", _RUN, str(n), str(i), str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )


def _result(proc: subprocess.Popen) -> dict:
    out, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err[-3000:]
    return json.loads(out.strip().splitlines()[-1])


def test_two_processes_agree_with_one():
    port = _free_port()
    procs = [_start(2, i, port) for i in range(2)]
    one = _start(1, 0, 0)
    first, second, alone = (_result(p) for p in (*procs, one))
    assert first["processes"] == 2 and first["devices"] == 2
    assert alone["processes"] == 1 and alone["devices"] == 1
    for res in (first, second):
        boxes, ref = np.asarray(res["boxes"]), np.asarray(alone["boxes"])
        assert boxes.shape == ref.shape == (3, 8, 4)
        # Every process returns the whole batch; each item ran the same program as alone.
        assert np.max(np.abs(boxes - ref)) < 0.05, np.max(np.abs(boxes - ref))
        assert res["lost"] == alone["lost"]
    # Different keys give different runs: the comparison above can fail.
    ref = np.asarray(alone["boxes"])
    assert np.max(np.abs(ref[0] - ref[1])) > 0.1
