import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import moirejax as mj
from moirejax._fileio import DataError

from .helpers import tree_allclose


@pytest.mark.parametrize("name", ["dense", "mid", "sparse"])
@pytest.mark.parametrize("layout", ["lines", "crossed"])
def test_device_json_round_trip(tmp_path, name, layout):
    device = mj.preset(name, layout=layout)
    path = tmp_path / "device.json"
    mj.save_device(path, device)
    loaded = mj.load_device(path)
    assert tree_allclose(device, loaded)
    assert loaded.layout == layout
    assert json.loads(path.read_text())["format"] == "moirejax-device"


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(p1=-0.3, p2=0.3), "pitches must be positive"),
        (dict(p1=0.35, p2=0.3, a=12.0, Z=12.0), "0 < a < Z"),
        (dict(p1=0.35, p2=0.3, duty1=1.0), "duty1"),
        (dict(p1=0.35, p2=0.3, elastomer=mj.Elastomer(thickness=5.0)), "exceeds the grating separation"),
        (dict(p1=0.35, p2=0.3, layout="hexagonal"), "layout"),
    ],
)
def test_device_invariants(kwargs, message):
    with pytest.raises(ValueError, match=message):
        mj.Device(**kwargs)


def test_elastomer_invariants():
    with pytest.raises(ValueError, match="nu"):
        mj.Elastomer(nu=0.5)
    with pytest.raises(ValueError, match="E must be positive"):
        mj.Elastomer(E=0.0)


def test_schema_rejects_bad_file(tmp_path):
    path = tmp_path / "bad.json"
    obj = mj.device_to_json(mj.preset("mid"))
    del obj["p1"]
    path.write_text(json.dumps(obj))
    with pytest.raises(DataError, match="p1"):
        mj.load_device(path)
    path.write_text("{not json")
    with pytest.raises(DataError, match="not valid JSON"):
        mj.load_device(path)


def test_device_is_a_pytree_of_arrays_under_jit():
    # Parameters are arrays, so a changed pitch does not recompile.
    device = mj.preset("mid")

    @jax.jit
    def period(d):
        return mj.moire_period(d.moire_wavevectors()[0])

    p_mid = period(device)
    p_other = period(mj.preset("sparse"))
    assert np.isclose(p_mid, 4.2) and np.isclose(p_other, 6.0)
    g = jax.grad(lambda d: mj.moire_period(d.moire_wavevectors()[0]))(device)
    assert jnp.isfinite(g.p1) and g.p1 > 0
