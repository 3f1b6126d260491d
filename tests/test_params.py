"""Parameters with their Props (``cpf_jax.params``): declaring, addressing, constraining."""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
import pytest

from cpf_jax import params as pp


class Inner(NamedTuple):
    scale: object
    share: object


class Outer(NamedTuple):
    inner: Inner
    offset: object
    count: object


SPEC = Outer(
    inner=Inner(scale=pp.P((2.0, 3.0), "softplus"), share=pp.P(0.25, "sigmoid")),
    offset=pp.P(-1.5),
    count=pp.P(30.0, "softplus", trainable=False),
)


def test_values_and_props_split_a_spec():
    values, props = pp.values(SPEC), pp.props(SPEC)
    np.testing.assert_array_equal(values.inner.scale, [2.0, 3.0])
    assert values.inner.scale.dtype == jnp.float32 and values.offset.dtype == jnp.float32
    assert props.inner.share == pp.Prop("sigmoid", True)
    assert props.count == pp.Prop("softplus", False)
    assert SPEC.inner.scale.value == (2.0, 3.0)  # the spec itself is plain data


def test_paths_get_and_replace_address_nested_fields():
    values, props = pp.values(SPEC), pp.props(SPEC)
    assert list(pp.paths(props)) == ["inner.scale", "inner.share", "offset", "count"]
    assert list(pp.paths(props, trainable_only=True)) == ["inner.scale", "inner.share", "offset"]
    assert float(pp.get(values, "inner.share")) == 0.25
    moved = pp.replace(values, "inner.share", jnp.float32(0.5))
    assert float(moved.inner.share) == 0.5 and float(values.inner.share) == 0.25
    assert moved.offset is values.offset
    with pytest.raises(ValueError, match="inner has fields scale, share"):
        pp.get(values, "inner.sigma")


def test_constrain_inverts_unconstrain_and_refuses_untrainable_paths():
    values, props = pp.values(SPEC), pp.props(SPEC)
    names = ["inner.scale", "inner.share", "offset"]
    free = pp.unconstrain(values, props, names)
    # softplus^-1(2) = log(e^2 - 1); logit(0.25) = log(1/3)
    np.testing.assert_allclose(free["inner.scale"][0], np.log(np.expm1(2.0)), rtol=1e-6)
    np.testing.assert_allclose(free["inner.share"], np.log(1.0 / 3.0), rtol=1e-6)
    back = pp.constrain(free, values, props)
    for name in names:
        np.testing.assert_allclose(pp.get(back, name), pp.get(values, name), rtol=1e-6)
    with pytest.raises(ValueError, match="'count' is not trainable"):
        pp.unconstrain(values, props, ["count"])
    # A group names the field that is not trainable.
    untrainable = props._replace(inner=props.inner._replace(share=pp.Prop("sigmoid", False)))
    with pytest.raises(ValueError, match="'inner.share' is not trainable"):
        pp.unconstrain(values, untrainable, ["inner"])
