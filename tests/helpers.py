"""Shared tolerances and numerical references for the test suite."""

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np


# float64 tolerances used by every gradient and identity check.
RTOL = 1e-6
ATOL = 1e-9
# Finite-difference gradients lose about half the digits.
FD_RTOL = 1e-5
FD_ATOL = 1e-7


def tree_allclose(x, y, *, rtol=RTOL, atol=ATOL):
    """`True` when two PyTrees have the same structure and all leaves are close."""
    if jtu.tree_structure(x) != jtu.tree_structure(y):
        return False
    xs, ys = jtu.tree_leaves(x), jtu.tree_leaves(y)
    return all(np.shape(a) == np.shape(b) and np.allclose(a, b, rtol=rtol, atol=atol) for a, b in zip(xs, ys))


def finite_difference_jvp(fn, primals, tangents, eps=1e-6):
    """Central-difference Jacobian-vector product of `fn` at `primals` along `tangents`.

    Works on PyTrees of arrays; use in float64 only.
    """
    plus = jtu.tree_map(lambda p, t: p + eps * t, primals, tangents)
    minus = jtu.tree_map(lambda p, t: p - eps * t, primals, tangents)
    f_plus = fn(*plus)
    f_minus = fn(*minus)
    out = fn(*primals)
    tangent_out = jtu.tree_map(lambda a, b: (a - b) / (2 * eps), f_plus, f_minus)
    return out, tangent_out


def check_grad_against_fd(fn, x, *, eps=1e-6, rtol=FD_RTOL, atol=FD_ATOL, key=None):
    """Compare `jax.jvp` of a scalar- or array-valued `fn` with central differences.

    Uses a random unit tangent over the inexact leaves of `x`.
    """
    key = jax.random.PRNGKey(0) if key is None else key
    dynamic, static = eqx.partition(x, eqx.is_inexact_array)
    leaves, treedef = jtu.tree_flatten(dynamic)
    keys = jax.random.split(key, len(leaves))
    tangent_leaves = [jax.random.normal(k, jnp.shape(l), jnp.result_type(l)) for k, l in zip(keys, leaves)]
    tangents = jtu.tree_unflatten(treedef, tangent_leaves)

    def f(d):
        return fn(eqx.combine(d, static))

    _, jvp_out = jax.jvp(f, (dynamic,), (tangents,))
    _, fd_out = finite_difference_jvp(f, (dynamic,), (tangents,), eps=eps)
    assert tree_allclose(jvp_out, fd_out, rtol=rtol, atol=atol), (jvp_out, fd_out)
