"""The checkpoint's state pytree (fitting/io/treeio.py): every supported leaf and container round-trips
through an HDF5 group with its type; a checkpoint of the older format is refused with a message."""

import dataclasses
import typing

import h5py
import jax.numpy as jnp
import numpy as np
import pytest

from jaxplush.errors import JaxplushError
from jaxplush.fitting import io as _io
from jaxplush.fitting.judge.outcome import Stop
from jaxplush.fitting.stages.search import LMState
from jaxplush.fitting.io.treeio import TreeError, conform, read_tree, write_tree


class Pair(typing.NamedTuple):
    a: object
    b: object


@dataclasses.dataclass(frozen=True)
class Frozen:
    x: object
    y: int = 0


@dataclasses.dataclass
class Mutable:
    items: list
    note: str = ""
    derived: object = dataclasses.field(default=None, init=False)


def _same(a, b):
    assert type(a) is type(b), (a, b)
    if isinstance(a, np.ndarray) or hasattr(a, "dtype") and hasattr(a, "shape") and not isinstance(a, np.generic):
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    elif dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            _same(getattr(a, f.name), getattr(b, f.name))
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            _same(x, y)
    elif isinstance(a, dict):
        assert list(a) == list(b)
        for k in a:
            _same(a[k], b[k])
    elif isinstance(a, float) and np.isnan(a):
        assert np.isnan(b)
    else:
        assert a == b


def test_every_leaf_and_container_round_trips_with_its_type(tmp_path):
    m = Mutable(items=[np.float32(1.5), np.int64(-3)], note="ü")
    m.derived = (None, "")
    tree = dict(
        none=None, yes=True, no=False, i=-7, big=2 ** 40, f=0.25, inf=float("inf"), nan=float("nan"), c=1 - 2j,
        s="", text="stopped by the callback", stop=Stop.CALLBACK, unset=Stop.NONE,
        f64=np.arange(6.0).reshape(2, 3), i32=np.arange(3, dtype=np.int32), flags=np.array([True, False]),
        empty=np.zeros((0, 2, 1)), scalar_array=np.array(4.0), jax=jnp.arange(3, dtype=jnp.float32),
        nested=[(1, [2, (3, None)]), [], ()], named=Pair(a=Pair(a=1, b="x"), b=[np.ones(2)]),
        frozen=Frozen(x={"k": [1.0, {"deep": Stop.STEP}]}), mutable=m,
        keys={1: "int key", "two": 2, 2.5: "float key", False: None},
        search=LMState(theta=np.ones((2, 1)), loss=0.5, history=[(0.5, np.ones((2, 1)))], stopped=Stop.SCREENED))
    with h5py.File(tmp_path / "t.h5", "w") as f:
        write_tree(f.create_group("state"), tree)
    with h5py.File(tmp_path / "t.h5", "r") as f:
        back = read_tree(f["state"])
    _same(tree, back)
    assert back["mutable"].derived == (None, "")         # a field outside __init__ too
    # a template gives the leaves its dtypes and array kinds, and must match the structure
    like = dict(a=jnp.zeros(3, jnp.float32), b=np.zeros(2, np.float64))
    got = conform(dict(a=np.arange(3.0), b=np.ones(2)), like)
    assert got["a"].dtype == jnp.float32 and isinstance(got["b"], np.ndarray)
    with pytest.raises(TreeError, match="structure"):
        conform(dict(a=np.arange(3.0)), like)


def test_what_cannot_be_written_is_refused(tmp_path):
    with h5py.File(tmp_path / "t.h5", "w") as f:
        with pytest.raises(TypeError, match="cannot write a object"):
            write_tree(f.create_group("a"), [object()])
        with pytest.raises(TypeError, match="root must be a container"):
            write_tree(f.create_group("b"), 1.0)


def test_a_checkpoint_of_the_older_format_is_refused_with_a_message(tmp_path):
    out = tmp_path / "FIT.h5"
    with h5py.File(out, "w") as f:
        g = f.create_group("checkpoint")
        g.attrs["settings"] = "{}"
        g.attrs["phase"] = "local"
    with pytest.raises(JaxplushError, match="written by an older jaxplush; run without --resume"):
        _io.load_checkpoint(out, None, {})


def test_a_dataclass_field_the_file_lacks_takes_its_default(tmp_path):
    """A state written before a field with a default existed (a search without ``updates``) reads
    back with that default; a field without a default cannot be made up."""
    import json
    st = LMState(theta=np.ones((2, 1)), loss=0.5, updates=3)
    with h5py.File(tmp_path / "t.h5", "w") as f:
        write_tree(f.create_group("state"), dict(search=st))
        g = f["state/0"]                 # (a dict keeps its values under their indices)
        leaves = json.loads(g.attrs["__leaves__"])
        del leaves["updates"]
        del g.attrs["updates"]
        g.attrs["__leaves__"] = json.dumps(leaves)
    with h5py.File(tmp_path / "t.h5", "r") as f:
        back = read_tree(f["state"])["search"]
    assert back.updates == 0 and back.loss == 0.5 and np.array_equal(back.theta, st.theta)
    with h5py.File(tmp_path / "t.h5", "a") as f:
        g = f["state/0"]                 # (a dict keeps its values under their indices)
        leaves = json.loads(g.attrs["__leaves__"])
        del leaves["loss"]
        del g.attrs["loss"]
        g.attrs["__leaves__"] = json.dumps(leaves)
    with h5py.File(tmp_path / "t.h5", "r") as f, pytest.raises(TreeError, match="LMState lacks its field 'loss'"):
        read_tree(f["state"])
