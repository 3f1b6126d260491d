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
# # cpf_jax quickstart: the colour layer
#
# Track a person's box in a synthetic Kinect-v2-like RGB-D sequence, score it against the
# ground truth, run several seeds and settings in one `vmap`, and look at the result.
# (This file is a jupytext notebook; `jupytext --to notebook quickstart.py` opens it in
# Jupyter. The test suite executes it.)

# %%
import os

import jax
import jax.numpy as jnp
import numpy as np

from cpf_jax import ColourConfig, Frame, build_colour_filter, default_colour_params, track_boxes
from cpf_jax import params as pp
from cpf_jax.metrics import format_summary, summarise
from cpf_jax.synthetic import make_sequence

N_FRAMES = int(os.environ.get("CPF_NOTEBOOK_FRAMES", "60"))

# %% [markdown]
# A synthetic sequence carries colour, depth, the ground-truth box per frame and 3D joints.

# %%
seq = make_sequence("walk_across_medium", seed=0, n_frames=N_FRAMES)
print(seq.colour.shape, seq.depth.dtype, seq.boxes[0], seq.joint_names[:4])
frames = Frame(jnp.asarray(seq.colour), jnp.asarray(seq.depth))

# %% [markdown]
# The static configuration (particle count, bins, motion model, histogram window) builds a
# filter; the continuous parameters are a separate pytree that gradients or `vmap` can touch,
# nested by term (`params.histogram.sigma`, `params.motion.tau`). `track_boxes` runs any box
# filter over the frames and returns `(boxes [T, 4], lost [T])`.

# %%
config = ColourConfig(n_particles=100).with_window(seq.boxes[0, 2:], seq.colour.shape[1:3])
filt = build_colour_filter(config)
params = default_colour_params()
# Arrays go in as arguments: closed over, they would be baked into the program as constants.
run = jax.jit(lambda key, frames, box: track_boxes(filt, params, key, frames, box))
boxes, _ = run(jax.random.PRNGKey(0), frames, seq.boxes[0])
boxes = np.asarray(boxes)
summary = summarise(boxes, seq.boxes, seq.visible)
print(format_summary({"walk_across_medium": summary}))

# %% [markdown]
# Four seeds at once with `vmap`, and a sweep over the likelihood width sigma (the parameter
# at the path `"histogram.sigma"`, replaced with `cpf_jax.params.replace`): one jitted
# program over a batch of (key, sigma) pairs serves both, so it compiles once. (The histogram
# kernel's exactness fallback stays a real branch under `vmap`: the whole batch takes the fast
# path when every member fits its window; `kernels.histogram.batch_all`.)

# %%
sweep = jax.jit(
    jax.vmap(
        lambda key, sigma, frames, box: track_boxes(
            filt, pp.replace(params, "histogram.sigma", sigma), key, frames, box
        )[0],
        in_axes=(0, 0, None, None),
    )
)
keys = jax.random.split(jax.random.PRNGKey(1), 4)
by_seed = sweep(keys, jnp.full(4, params.histogram.sigma), frames, seq.boxes[0])
print(
    "success per seed:",
    [round(summarise(np.asarray(b), seq.boxes)["success_rate"], 1) for b in by_seed],
)
sigmas = jnp.array([0.05, 0.1, 0.3, 1.0])
by_sigma = sweep(jnp.stack([keys[0]] * 4), sigmas, frames, seq.boxes[0])
for s, b in zip(sigmas, by_sigma, strict=True):
    print(
        f"sigma={float(s):.2f}: success {summarise(np.asarray(b), seq.boxes)['success_rate']:.1f} %"
    )

# %% [markdown]
# A contact sheet of the track (green) against the ground truth (red).

# %%
import cv2  # noqa: E402

tiles = []
for t in np.linspace(0, N_FRAMES - 1, 4).astype(int):
    img = seq.colour[t].copy()
    for b, c in ((seq.boxes[t], (255, 0, 0)), (boxes[t], (0, 255, 0))):
        x, y, w, h = (int(round(v)) for v in b)
        cv2.rectangle(img, (x, y), (x + w, y + h), c, 2)
    tiles.append(img)
sheet = np.hstack(tiles)
print("contact sheet", sheet.shape)

# %% [markdown]
# The OTB success plot of each sigma's run (`run_success_curve` scores a run by the rules of
# `summarise`; its mean is the AUC), drawn with `cpf_jax.charts` (OpenCV, BGR image).

# %%
from cpf_jax import charts  # noqa: E402
from cpf_jax.metrics import run_success_curve  # noqa: E402

curves = {
    f"sigma {float(s):.2f}": run_success_curve(np.asarray(b), seq.boxes, seq.visible)
    for s, b in zip(sigmas, by_sigma, strict=True)
}
plot = charts.success_plot(curves, title="walk_across_medium, one seed per sigma")
print("success plot", plot.shape, {k: round(100 * float(v.mean()), 1) for k, v in curves.items()})
