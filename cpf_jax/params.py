"""Continuous parameters: values, their constraints and trainable flags, side by side.

A filter's parameters are a tree of ``NamedTuple`` s, one per term of its model
(``ColourParams(motion=..., histogram=..., contrast=...)``); its leaves are float32
arrays. Beside each value sits its ``Prop`` (dynamax's ``ParameterProperties``): the
bijector that maps the tuner's free value into the parameter's domain, and whether
gradients may move it. A term declares both at once, with ``P`` leaves::

    HISTOGRAM = HistogramParams(sigma=P(0.15, "softplus"), lost_distance=P(0.7, "sigmoid"))

``values(spec)`` builds the parameter tree (float32 arrays, created when called, so that
importing the library starts no JAX backend) and ``props(spec)`` the matching tree of
``Prop`` s that ``cpf_jax.tuning`` reads. Fields are addressed by dotted paths
(``"histogram.sigma"``, ``"motion.tau"``) with :func:`get` and :func:`replace`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

__all__ = [
    "BIJECTORS",
    "P",
    "Prop",
    "values",
    "props",
    "get",
    "replace",
    "paths",
    "constrain",
    "unconstrain",
]


def _softplus_inverse(p: Array) -> Array:
    # log(exp(p) - 1), stable for large p: p + log(1 - exp(-p)).
    p = jnp.asarray(p, jnp.float32)
    return p + jnp.log(-jnp.expm1(-p))


def _logit(p: Array) -> Array:
    p = jnp.asarray(p, jnp.float32)
    return jnp.log(p) - jnp.log1p(-p)


#: ``constraint -> (constrain, unconstrain)``: maps between the optimiser's free values
#: and the parameters' domains (positive: ``"softplus"``; ``(0, 1)``: ``"sigmoid"``).
BIJECTORS: dict[str, tuple[Callable[[Array], Array], Callable[[Array], Array]]] = {
    "identity": (lambda u: u, lambda p: jnp.asarray(p, jnp.float32)),
    "softplus": (jax.nn.softplus, _softplus_inverse),
    "sigmoid": (jax.nn.sigmoid, _logit),
}


class Prop(NamedTuple):
    """How one parameter is tuned: its bijector (a key of ``BIJECTORS``) and whether
    gradients may move it (counts, thresholds that act only through comparisons and
    fixed matrices are not trainable)."""

    constraint: str = "identity"
    trainable: bool = True


class P(NamedTuple):
    """A parameter's default value with its ``Prop``, as a term declares it."""

    value: Any
    constraint: str = "identity"
    trainable: bool = True


def _is_p(x: Any) -> bool:
    return isinstance(x, P)


def _is_prop(x: Any) -> bool:
    return isinstance(x, Prop)


def _value(p: P) -> Any:
    return None if p.value is None else jnp.asarray(p.value, jnp.float32)


def values(spec: Any) -> Any:
    """The parameter tree of a tree of ``P`` leaves: each value as a float32 array."""
    return jax.tree_util.tree_map(_value, spec, is_leaf=_is_p)


def props(spec: Any) -> Any:
    """The ``Prop`` tree of a tree of ``P`` leaves (same structure as ``values(spec)``)."""
    return jax.tree_util.tree_map(lambda p: Prop(p.constraint, p.trainable), spec, is_leaf=_is_p)


def _parts(path: str) -> list[str]:
    return [p for p in path.split(".") if p]


def get(tree: Any, path: str) -> Any:
    """The field at a dotted ``path`` of a tree of ``NamedTuple`` s (``"motion.tau"``); a
    path that does not exist is a ``ValueError`` naming the fields there are."""
    node = tree
    for i, name in enumerate(_parts(path)):
        fields = getattr(node, "_fields", ())
        if name not in fields:
            where = ".".join(_parts(path)[:i]) or "the parameters"
            raise ValueError(f"no parameter {path!r}: {where} has fields {', '.join(fields)}")
        node = getattr(node, name)
    return node


def replace(tree: Any, path: str, value: Any) -> Any:
    """``tree`` with the field at the dotted ``path`` replaced by ``value``."""
    names = _parts(path)
    if not names:
        return value
    get(tree, path)  # a clear ValueError for a path that does not exist
    head, rest = names[0], ".".join(names[1:])
    return tree._replace(**{head: replace(getattr(tree, head), rest, value)})


def paths(prop_tree: Any, trainable_only: bool = False) -> Iterator[str]:
    """Dotted paths of every ``Prop`` leaf of ``prop_tree`` (in field order)."""

    def walk(node: Any, prefix: str) -> Iterator[str]:
        if _is_prop(node):
            if node.trainable or not trainable_only:
                yield prefix
            return
        for name in getattr(node, "_fields", ()):
            yield from walk(getattr(node, name), f"{prefix}.{name}" if prefix else name)

    yield from walk(prop_tree, "")


def _props_at(prop_tree: Any, path: str) -> Any:
    node = get(prop_tree, path)
    if node is None:
        raise ValueError(f"parameter {path!r} has no properties")
    return node


def _map(index: int, prop_node: Any, value: Any) -> Any:
    """Apply each ``Prop``'s bijector (``index`` 0: constrain, 1: unconstrain) to the
    matching part of ``value``."""

    def one(prop: Prop, v: Any) -> Any:
        if v is None:
            return None
        return jax.tree_util.tree_map(BIJECTORS[prop.constraint][index], v)

    return jax.tree_util.tree_map(one, prop_node, value, is_leaf=_is_prop)


def _check_trainable(prop_tree: Any, path: str) -> Any:
    node = _props_at(prop_tree, path)
    for sub in [""] if _is_prop(node) else list(paths(node)):
        prop = node if not sub else get(node, sub)
        name = f"{path}.{sub}" if sub else path
        if not _is_prop(prop) or prop.constraint not in BIJECTORS:
            raise ValueError(f"parameter {name!r}: unknown constraint {prop!r}")
        if not prop.trainable:
            raise ValueError(f"parameter {name!r} is not trainable (its Prop says so)")
    return node


def unconstrain(params: Any, prop_tree: Any, names: list[str] | tuple[str, ...]) -> dict:
    """``{path: free value}`` of the parameters at ``names`` (the optimiser's variables)."""
    return {n: _map(1, _check_trainable(prop_tree, n), get(params, n)) for n in names}


def constrain(free: dict, params: Any, prop_tree: Any) -> Any:
    """``params`` with the fields of ``free`` (``{path: free value}``) mapped back into
    their domains."""
    for n, u in free.items():
        params = replace(params, n, _map(0, _check_trainable(prop_tree, n), u))
    return params
