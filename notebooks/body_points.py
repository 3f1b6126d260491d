# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Body points: the cascade
#
# Layer 1 tracks the person's box (here the RGB-D grid filter with occlusion flags); layer 2
# segments the body in depth inside that box and tracks points on it (head, hands, feet)
# with spin images and geodesic distances. Both layers run in one jitted step. This
# notebook finds the points to track on its own (`find_body_points`), tracks them through a
# synthetic walk towards the camera, and scores them against the sequence's 3D joints.
# (A jupytext notebook: `jupytext --to notebook body_points.py` opens it in Jupyter.)

# %%
import os

import jax
import jax.numpy as jnp
import numpy as np

from cpf_jax import params as pp
from cpf_jax.cascade import CascadeConfig, build_cascade, default_cascade_params, find_body_points
from cpf_jax.filter import Context, track
from cpf_jax.kernels.background import median_background
from cpf_jax.metrics import format_summary, summarise
from cpf_jax.points import AUTO_POINTS, BODY_POINT_DEPTH_OFFSET_MM, PointConfig
from cpf_jax.rgbd import RGBDConfig
from cpf_jax.synthetic import make_sequence
from cpf_jax.types import Frame

N_FRAMES = int(os.environ.get("CPF_NOTEBOOK_FRAMES", "45"))

# %% [markdown]
# A walker coming towards the camera at 30 frames/s, and the empty room as the background
# model (with a real camera: `median_background` of frames before the person walks in).

# %%
seq = make_sequence("walk_towards", seed=0, n_frames=N_FRAMES, fps=30.0)
frames = Frame(jnp.asarray(seq.colour), jnp.asarray(seq.depth))
background = median_background(
    jnp.asarray(seq.meta["background_colour"])[None],
    jnp.asarray(seq.meta["background_depth"])[None],
)

# %% [markdown]
# The cascade's configuration: layer 1 with a histogram window sized from the first box,
# layer 2 taking the body from the foreground (side-on, a body touches the furniture in
# depth, so depth alone would not separate them).

# %%
box_config = RGBDConfig(variant="grid-occlusion", n_particles=150).with_window(
    tuple(float(v) for v in seq.boxes[0, 2:]), seq.colour.shape[1:3]
)
point_config = PointConfig(n_particles=64).with_foreground()
config = CascadeConfig(box=box_config, points=point_config, foreground=True)

# %% [markdown]
# Where to start: the head above the neck, then the four geodesic extremities of the body
# seen from its centroid and head; the two lowest are the feet. `reach` is each
# extremity's geodesic distance (mm) from the rest: a hand hidden behind the body would
# show up as a short reach.

# %%
find = jax.jit(find_body_points, static_argnums=0)
first = Frame(frames.colour[0], frames.depth[0])
points0, reach = find(config, first, jnp.asarray(seq.boxes[0]), background)
for name, (x, y) in zip(AUTO_POINTS, np.asarray(points0), strict=True):
    print(f"{name:7s} at ({x:5.1f}, {y:5.1f})")
print("reach of hands and feet (mm):", np.asarray(reach).round(0))

# %% [markdown]
# Track both layers over the sequence: `track` runs the step as one `lax.scan`, with the
# background and the points to track in its `Context`. The tracked points are surface
# points; `estimate.joint_depth_offset` pushes each 3D estimate to the joint behind the
# surface (head 80 mm, hands 20, feet 40).

# %%
filt = build_cascade(config)
params = default_cascade_params(config)
offset = jnp.asarray(BODY_POINT_DEPTH_OFFSET_MM, jnp.float32)
params = pp.replace(params, "points.estimate.joint_depth_offset", offset)


def run(key, frames, box, points, background):
    # Arrays come in as arguments, not closed over: XLA would fold them as constants.
    context = Context(background=background, points=points)
    return track(filt, params, key, frames, box, context)[1]


info = jax.jit(run)(jax.random.PRNGKey(0), frames, jnp.asarray(seq.boxes[0]), points0, background)
summary = summarise(np.asarray(info.estimate), seq.boxes[1:], seq.visible[1:])
print(format_summary({"walk_towards (layer 1)": summary}))

# %% [markdown]
# Score the points against the 3D joints. "a" and "b" are image left and right at the start:
# facing the camera, the person's left hand is on the image's right. The hand points start
# at the fingertips (the extremities), a few centimetres from the hand joints the sequence
# records, so their errors include that offset (started on the joints' own pixels, the
# same walk gives about 29 mm: tests/test_cascade.py).

# %%
names = list(seq.joint_names)
start = seq.joints2d[0]
pairs = {"head": "head"}
for part in ("hand", "foot"):
    left, right = names.index(f"left_{part}"), names.index(f"right_{part}")
    a, b = (left, right) if start[left, 0] < start[right, 0] else (right, left)
    pairs[f"{part}_a"], pairs[f"{part}_b"] = names[a], names[b]
mean3d = np.asarray(info.points.mean3d)  # [T-1, 5, 3] mm
errors = {}
for k, name in enumerate(AUTO_POINTS):
    truth = seq.joints3d[1:, names.index(pairs[name])]
    errors[name] = float(np.nanmedian(np.linalg.norm(mean3d[:, k] - truth, axis=-1)))
    print(f"{name:7s} ({pairs[name]:10s}) median 3D error {errors[name]:6.1f} mm")
summary["point_errors_mm"] = errors

# %% [markdown]
# The body layer 2 saw in the last frame, as a point cloud (camera mm; log it to Rerun with
# `cpf_jax.viz.RerunLogger.log_points3d`, as `cpf-track --points` does).

# %%
from cpf_jax.cascade import body_surface  # noqa: E402

last = Frame(frames.colour[-1], frames.depth[-1])
cloud = jax.jit(body_surface, static_argnums=0)(config, last, info.box_used[-1], background)
cloud = np.asarray(cloud)
cloud = cloud[np.all(np.isfinite(cloud), axis=1)]
print(f"{len(cloud)} body points, depth {cloud[:, 2].min():.0f}-{cloud[:, 2].max():.0f} mm")
