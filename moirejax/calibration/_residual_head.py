"""The learned residual: a small MLP that corrects what the physics leaves.

Its inputs are the physical estimate (wrench over the paper's ranges, contact centre
and log radius); its output is a correction in the same scaled units. The last layer
starts at zero, so an untrained head is the identity, and training stops early on a
held-out split, so it learns systematic residuals rather than noise.
"""

import json
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from .._conventions import WRENCH_SCALE
from .._fileio import atomic_write_bytes, atomic_write_text


N_FEATURES = 9


def head_features(wrench: np.ndarray, x0: np.ndarray, y0: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Head inputs from physical estimates: `(n, 9)`."""
    return np.concatenate(
        [wrench / WRENCH_SCALE, (x0 / 10.0)[:, None], (y0 / 10.0)[:, None], np.log(np.maximum(radius, 1e-3))[:, None]],
        axis=1,
    )


class ResidualHead(eqx.Module):
    """MLP correction of a physical wrench estimate (see the module docstring)."""

    mlp: eqx.nn.MLP
    width: int = eqx.field(static=True)
    depth: int = eqx.field(static=True)

    def __init__(self, key, width: int = 32, depth: int = 2):
        mlp = eqx.nn.MLP(N_FEATURES, 6, width, depth, activation=jax.nn.gelu, key=key)
        last = mlp.layers[-1]
        self.mlp = eqx.tree_at(
            lambda m: (m.layers[-1].weight, m.layers[-1].bias),
            mlp,
            (jnp.zeros_like(last.weight), jnp.zeros_like(last.bias)),
        )
        self.width = width
        self.depth = depth

    def __call__(self, features):
        return self.mlp(features)

    def correct(self, wrench: np.ndarray, x0: np.ndarray, y0: np.ndarray, radius: np.ndarray) -> np.ndarray:
        """Corrected wrenches `(n, 6)` in N and N·m."""
        # In the head's own precision: a head saved in float32 also corrects float64 runs.
        dtype = self.mlp.layers[0].weight.dtype
        features = jnp.asarray(head_features(wrench, x0, y0, radius), dtype=dtype)
        return wrench + np.asarray(jax.vmap(self)(features), dtype=np.float64) * WRENCH_SCALE


def train_residual_head(
    features: np.ndarray,
    targets: np.ndarray,
    *,
    validation: float = 0.2,
    steps: int = 3000,
    patience: int = 20,
    seed: int = 0,
) -> tuple[ResidualHead, dict]:
    """Fit a [`ResidualHead`][] to `targets - physical estimate` (both scaled), with early
    stopping on a held-out `validation` fraction. Returns the head and its training record."""
    rng = np.random.default_rng(seed)
    n = len(features)
    order = rng.permutation(n)
    n_val = max(1, int(round(validation * n)))
    val, train = order[:n_val], order[n_val:]
    x = jnp.asarray(features, dtype=float)
    y = jnp.asarray(targets, dtype=float)
    head = ResidualHead(jax.random.PRNGKey(seed))
    optimiser = optax.adamw(3e-3, weight_decay=1e-4)
    state = optimiser.init(eqx.filter(head, eqx.is_inexact_array))

    def loss(model, idx):
        prediction = jax.vmap(model)(x[idx])
        return jnp.mean((prediction - y[idx]) ** 2)

    @eqx.filter_jit
    def step(model, state):
        with jax.numpy_dtype_promotion("standard"):
            value, grads = eqx.filter_value_and_grad(loss)(model, train)
            updates, state = optimiser.update(grads, state, eqx.filter(model, eqx.is_inexact_array))
            model = eqx.apply_updates(model, updates)
        return model, state, value

    best, best_loss, waited, record = head, float(loss(head, val)), 0, []
    initial_val = best_loss
    for i in range(steps):
        head, state, train_loss = step(head, state)
        if i % 25 == 0:
            val_loss = float(loss(head, val))
            record.append((i, float(train_loss), val_loss))
            if val_loss < best_loss - 1e-7:
                best, best_loss, waited = head, val_loss, 0
            else:
                waited += 1
                if waited >= patience:
                    break
    return best, {
        "validation_mse_before": initial_val,
        "validation_mse_after": best_loss,
        "steps": record[-1][0] if record else 0,
    }


def save_head(path: str | Path, head: ResidualHead) -> None:
    """Write the head's weights (equinox serialisation) and its hyperparameters beside them."""
    import io

    buffer = io.BytesIO()
    eqx.tree_serialise_leaves(buffer, head)
    atomic_write_bytes(path, buffer.getvalue())
    dtype = str(jax.tree_util.tree_leaves(eqx.filter(head, eqx.is_inexact_array))[0].dtype)
    meta = {"width": head.width, "depth": head.depth, "dtype": dtype}
    atomic_write_text(str(path) + ".json", json.dumps(meta) + "\n")


def load_head(path: str | Path) -> ResidualHead:
    """Read a head written by [`save_head`][], in the precision it was saved in (a head
    trained in float32 loads under `jax_enable_x64` too)."""
    meta = json.loads(Path(str(path) + ".json").read_text())
    skeleton = ResidualHead(jax.random.PRNGKey(0), width=meta["width"], depth=meta["depth"])
    dtype = jnp.dtype(meta.get("dtype", "float32"))
    skeleton = jax.tree_util.tree_map(lambda x: x.astype(dtype) if eqx.is_inexact_array(x) else x, skeleton)
    with open(path, "rb") as f:
        return eqx.tree_deserialise_leaves(f, skeleton)
