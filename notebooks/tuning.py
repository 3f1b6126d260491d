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
# # Tuning the colour likelihood with gradients (optax)
#
# Start from a poor, hand-set likelihood (the thesis's sigma = 1 and a weak colour-contrast
# term), tune it by gradient descent on synthetic training walks, and check the result on a
# walk the tuner never saw. `cpf_jax.tuning` differentiates the DIoU loss of the tracked
# boxes through the particle filter, resampling included (see its module docstring).

# %%
import os

import jax
import jax.numpy as jnp
import numpy as np
import optax

from cpf_jax import (
    ColourConfig,
    Frame,
    build_colour_filter,
    default_colour_params,
    track_boxes,
    tuning,
)
from cpf_jax.colour import COLOUR_PROPS
from cpf_jax.metrics import summarise
from cpf_jax.synthetic import make_sequence

N_FRAMES = int(os.environ.get("CPF_NOTEBOOK_FRAMES", "60"))
STEPS = 6 if N_FRAMES < 30 else 30

# %% [markdown]
# Training data: short clips of two scenarios with training scene seeds (100, 101), all of
# one length, stacked into one batch. The config's histogram window must hold every box.

# %%
train = [
    make_sequence(name, seed=s, n_frames=N_FRAMES)
    for name in ("walk_across_fast", "walk_towards")
    for s in (100, 101)
]
data = tuning.stack_sequences(train)
largest = (
    max(float(s.boxes[:, 2].max()) for s in train),
    max(float(s.boxes[:, 3].max()) for s in train),
)
config = ColourConfig(n_particles=100).with_window(largest, train[0].colour.shape[1:3])
defaults = default_colour_params()
start = defaults._replace(
    histogram=defaults.histogram._replace(sigma=jnp.float32(1.0)),
    contrast=defaults.contrast._replace(weight=jnp.float32(5.0)),
)

# %% [markdown]
# Tune sigma and the contrast weight, named by their paths in the parameter tree. Each step
# draws fresh filter seeds, so the loss per step is noisy; the optimiser works on
# unconstrained values (`COLOUR_PROPS` gives each parameter's bijector: softplus for both).

# %%
result = tuning.tune(
    tuning.runner(build_colour_filter(config)),
    start,
    COLOUR_PROPS,
    data,
    names=("histogram.sigma", "contrast.weight"),
    optimizer=optax.adam(0.2),
    steps=STEPS,
)
for e in result.history:
    print(
        f"step {e['step']:2d} loss {e['loss']:.3f} sigma {e['histogram.sigma']:.3f} "
        f"contrast weight {e['contrast.weight']:.2f}"
    )

# %% [markdown]
# Held out: another scene seed of a third scenario, before and after.

# %%
test = make_sequence("walk_across_medium", seed=0, n_frames=N_FRAMES)
frames = Frame(jnp.asarray(test.colour), jnp.asarray(test.depth))
filt = build_colour_filter(config)
keys = jax.random.split(jax.random.PRNGKey(7), 3)
# One jitted run, parameters and key as arguments: one compile for both parameter sets.
run = jax.jit(lambda p, k: track_boxes(filt, p, k, frames, test.boxes[0])[0])
for label, p in (("hand-set", start), ("tuned", result.params)):
    rates = [summarise(np.asarray(run(p, k)), test.boxes)["success_rate"] for k in keys]
    print(f"{label}: held-out success rate {np.mean(rates):.1f} % over {len(keys)} seeds")
