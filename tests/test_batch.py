"""run_sharded and track_sharded: items spread over a device mesh equal the same items run
on one device, key by key (``run_sharded`` with the map inner loop, ``track_sharded``
with vmap).

Several devices are tested in a subprocess started with
``XLA_FLAGS=--xla_force_host_platform_device_count=2`` (the flag must be set before
JAX starts, so not in this process)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cpf_jax.batch import batch_mesh, run_sharded


def _affine(x, scale):
    return {"y": x["a"] * scale + x["b"][:, 0], "n": jnp.sum(x["b"])}


@pytest.mark.parametrize("inner", ["map", "vmap"])
def test_run_sharded_matches_numpy(inner):
    rng = np.random.default_rng(0)
    batched = {"a": rng.normal(size=(5, 3)).astype(np.float32), "b": rng.normal(size=(5, 3, 2))}
    batched["b"] = batched["b"].astype(np.float32)
    out = run_sharded(_affine, batched, 2.0, inner=inner)
    np.testing.assert_allclose(out["y"], batched["a"] * 2.0 + batched["b"][:, :, 0], rtol=1e-6)
    np.testing.assert_allclose(out["n"], batched["b"].sum(axis=(1, 2)), rtol=1e-5)
    assert out["y"].shape == (5, 3) and out["n"].shape == (5,)


def test_run_sharded_errors():
    with pytest.raises(ValueError, match="inner"):
        run_sharded(_affine, {"a": np.zeros((2, 1)), "b": np.zeros((2, 1, 1))}, 1.0, inner="pmap")
    with pytest.raises(ValueError, match="differ in batch size"):
        run_sharded(_affine, {"a": np.zeros((2, 1)), "b": np.zeros((3, 1, 1))}, 1.0)
    with pytest.raises(ValueError, match="leading batch axis"):
        run_sharded(lambda x: x, np.float32(1.0))
    with pytest.raises(ValueError, match="empty"):
        run_sharded(lambda x: x, np.zeros((0, 2)))
    with pytest.raises(ValueError, match="no arrays"):
        run_sharded(lambda x: x, {})
    mesh2d = jax.sharding.Mesh(
        np.asarray(jax.devices()[:1], dtype=object).reshape(1, 1), ("a", "b")
    )
    with pytest.raises(ValueError, match="one-axis mesh"):
        run_sharded(lambda x: x, np.zeros((2, 2)), mesh=mesh2d)
    with pytest.raises(ValueError, match="at least one device"):
        batch_mesh([])


_TWO_DEVICES = textwrap.dedent(
    """
    import json
    import jax, jax.numpy as jnp, numpy as np
    from cpf_jax.batch import batch_mesh, run_sharded, track_sharded
    from cpf_jax.colour import ColourConfig, build_colour_filter, default_colour_params
    from cpf_jax.filter import track_boxes
    from cpf_jax.synthetic import make_sequence
    from cpf_jax.types import Frame

    seq = make_sequence("walk_across_fast", seed=1, n_frames=10)
    frames = Frame(jnp.asarray(seq.colour), jnp.asarray(seq.depth))
    config = ColourConfig(n_particles=64).with_window(seq.boxes[0, 2:], seq.colour.shape[1:3])
    filt, params = build_colour_filter(config), default_colour_params()

    def one(key, frames, box):
        return track_boxes(filt, params, key, frames, box)

    keys = jax.random.split(jax.random.PRNGKey(0), 3)  # odd: one item of padding
    box = jnp.asarray(seq.boxes[0])
    # The one-device references use the same inner loop as the sharded run: vmap and
    # lax.map order a step's float sums differently, and resampling grows that rounding.
    reference, _ = jax.jit(lambda ks: jax.lax.map(lambda k: one(k, frames, box), ks))(keys)
    vmapped, vmapped_lost = jax.jit(jax.vmap(lambda k: one(k, frames, box)))(keys)
    # any box filter over keys (run_sharded over the keys), here with the vmap inner loop
    tracked, tracked_lost = track_sharded(filt, params, keys, frames, box, inner="vmap")
    # many sequences: the frames are batched too (the map inner loop)
    two = jax.tree.map(lambda a: jnp.stack([a, a]), frames)
    both, _ = run_sharded(lambda item: one(*item), (keys[:2], two, jnp.stack([box, box])))
    print(json.dumps({
        "devices": len(jax.devices()),
        "mesh": int(batch_mesh().devices.size),
        "max_diff_tracked": float(jnp.max(jnp.abs(tracked - vmapped))),
        "max_diff_sequences": float(jnp.max(jnp.abs(both - reference[:2]))),
        "lost_equal": bool(jnp.all(tracked_lost == vmapped_lost)),
        "seeds_differ": float(jnp.max(jnp.abs(reference[0] - reference[1]))),
        "shape": list(tracked.shape),
        "lost_shape": list(tracked_lost.shape),
        "finite": bool(jnp.all(jnp.isfinite(tracked))),
    }))
    """
)


def test_two_cpu_devices_match_one_device():
    env = dict(os.environ)
    flags = env.get("XLA_FLAGS", "")
    env["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count=2".strip()
    env["JAX_PLATFORMS"] = "cpu"
    run = subprocess.run(
        [sys.executable, "-c", _TWO_DEVICES], capture_output=True, text=True, env=env, timeout=600
    )
    assert run.returncode == 0, run.stderr[-2000:]
    res = json.loads(run.stdout.strip().splitlines()[-1])
    assert res["devices"] == 2 and res["mesh"] == 2
    assert res["shape"] == [3, 10, 4] and res["lost_shape"] == [3, 10] and res["finite"]
    # Rounding differs with the batch layout and the XLA flags and resampling grows it: the
    # bound is far below what a wrong key or item gives (seeds_differ, pixels).
    assert res["max_diff_tracked"] < 0.05, res
    assert res["max_diff_sequences"] < 0.05, res
    assert res["lost_equal"] and res["seeds_differ"] > 0.1, res
