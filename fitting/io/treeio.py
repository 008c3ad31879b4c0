"""A state pytree to and from an HDF5 group: what a fit's checkpoint holds.

:func:`write_tree` writes a tree of nested containers into a group and :func:`read_tree` rebuilds
it with the same types. Containers: dataclasses (frozen or not), NamedTuples, lists, tuples and
dicts (keys str, int, float or bool). Leaves: numpy arrays and jax arrays (datasets, dtype and
shape kept), numpy scalars, Python bool, int, float and complex, str, None, and enum members
(:class:`jaxplush.fitting.judge.outcome.Stop`; attributes), and warning notes
(:class:`jaxplush.errors.Note`: the text, its category recorded as ``note:module:qualname``).

Layout: a container is a group with the attribute ``__node__`` (its kind), ``__type__`` (the
class, ``module:qualname``, of a dataclass or NamedTuple) and ``__leaves__`` (JSON: child name ->
the kind of each leaf child, an enum's ``enum:module:qualname``); a child is named by its field,
or by its index in a list, tuple or dict (a dict's keys are the JSON attribute ``__keys__``, a
list's or tuple's length ``__length__``); names beginning with ``__`` are the layout's own. Scalar leaves are attributes of their
container, array leaves datasets, containers subgroups. A class is looked up among the modules
already imported (jaxplush's own are imported on demand); nothing in a file runs code.
"""

from __future__ import annotations

import dataclasses
import enum
import importlib
import json
import sys

import numpy as np

from jaxplush.errors import Note

#: Scalar leaf types and the kind each is recorded as.
_SCALARS = {bool: "bool", int: "int", float: "float", complex: "complex", str: "str"}


class TreeError(ValueError):
    """A group that does not hold a tree this reader can rebuild (damaged, or another version's)."""


def _type_name(cls):
    return f"{cls.__module__}:{cls.__qualname__}"


#: Modules of jaxplush.fitting that moved into its subpackages, by their old names: a file
#: written before names its classes there (a checkpoint resumed across the move).
MOVED = {f"jaxplush.fitting.{old}": f"jaxplush.fitting.{new}" for old, new in (
    ("kinds", "targets.kinds"), ("losses", "objective.losses"), ("problem", "objective.problem"),
    ("evaluate", "objective.evaluate"), ("shooting", "objective.shooting"), ("search", "stages.search"),
    ("lmfit", "stages.lmfit"), ("objects", "stages.objects"), ("equation_error", "stages.equation_error"),
    ("gradfit", "stages.gradfit"), ("field", "stages.field"), ("outcome", "judge.outcome"),
    ("intervals", "judge.intervals"), ("identifiability", "judge.identifiability"), ("result", "judge.result"),
    ("treeio", "io.treeio"))}


def _lookup(name):
    """The class ``module:qualname`` from a module already imported (or one of jaxplush's)."""
    module, _, qual = name.partition(":")
    module = MOVED.get(module, module)
    mod = sys.modules.get(module)
    if mod is None and module.split(".")[0] == "jaxplush":
        mod = importlib.import_module(module)
    if mod is None:
        raise TreeError(f"type {name}: module {module} is not imported")
    obj = mod
    for part in qual.split("."):
        obj = getattr(obj, part, None)
        if obj is None:
            raise TreeError(f"type {name} not found")
    return obj


def _is_namedtuple(x):
    return isinstance(x, tuple) and hasattr(type(x), "_fields")


def _children(tree):
    """(node kind, type name or None, [(child name, value)], extra attributes) of a container."""
    if dataclasses.is_dataclass(tree) and not isinstance(tree, type):
        return "dataclass", _type_name(type(tree)), [(f.name, getattr(tree, f.name))
                                                     for f in dataclasses.fields(tree)], {}
    if _is_namedtuple(tree):
        return "namedtuple", _type_name(type(tree)), list(zip(tree._fields, tree)), {}
    if type(tree) in (list, tuple):
        return type(tree).__name__, None, [(str(i), v) for i, v in enumerate(tree)], {"__length__": len(tree)}
    if type(tree) is dict:
        keys = list(tree)
        if not all(type(k) in (str, int, float, bool) for k in keys):
            raise TypeError(f"write_tree: dict keys must be str, int, float or bool, got {keys!r}")
        return "dict", None, [(str(i), tree[k]) for i, k in enumerate(keys)], {"__keys__": json.dumps(keys)}
    return None


def _leaf_kind(x):
    if x is None:
        return "none"
    if isinstance(x, enum.Enum):
        return "enum:" + _type_name(type(x))
    if isinstance(x, Note):
        return "note:" + _type_name(x.category)
    if type(x) in _SCALARS:
        return _SCALARS[type(x)]
    if isinstance(x, np.ndarray):
        return "ndarray"
    if isinstance(x, np.generic):
        return "numpy:" + x.dtype.str
    if type(x).__module__.startswith("jax") and hasattr(x, "dtype") and hasattr(x, "shape"):
        return "jax"
    raise TypeError(f"write_tree: cannot write a {type(x).__name__} ({x!r:.80})")


def write_tree(group, tree):
    """Write ``tree`` (a container: see the module docstring) into the h5py ``group``."""
    node = _children(tree)
    if node is None:
        raise TypeError(f"write_tree: the root must be a container, got {type(tree).__name__}")
    kind, type_name, children, extra = node
    group.attrs["__node__"] = kind
    if type_name is not None:
        group.attrs["__type__"] = type_name
    for k, v in extra.items():
        group.attrs[k] = v
    leaves = {}
    for name, value in children:
        if name.startswith("__"):
            raise TypeError(f"write_tree: field name {name!r}: names beginning with '__' are the layout's own")
        if _children(value) is not None:
            write_tree(group.create_group(name), value)
            continue
        leaves[name] = leaf = _leaf_kind(value)
        if leaf in ("ndarray", "jax"):
            group.create_dataset(name, data=np.asarray(value))
        elif leaf.startswith("enum:"):
            group.attrs[name] = value.value
        elif leaf.startswith("note:"):
            group.attrs[name] = str(value)
        elif leaf != "none":
            group.attrs[name] = value
    group.attrs["__leaves__"] = json.dumps(leaves)


def _read_leaf(group, name, kind):
    if kind == "none":
        return None
    if kind == "ndarray":
        return np.asarray(group[name][()])
    if kind == "jax":
        import jax.numpy as jnp
        return jnp.asarray(group[name][()])
    v = group.attrs[name]
    if kind.startswith("enum:"):
        return _lookup(kind[5:])(v.decode() if isinstance(v, bytes) else v)
    if kind.startswith("note:"):
        return Note(v.decode() if isinstance(v, bytes) else str(v), _lookup(kind[5:]))
    if kind.startswith("numpy:"):
        return np.dtype(kind[6:]).type(v)
    if kind == "str":
        return v.decode() if isinstance(v, bytes) else str(v)
    if kind in ("bool", "int", "float", "complex"):
        return {"bool": bool, "int": int, "float": float, "complex": complex}[kind](v)
    raise TreeError(f"unknown leaf kind {kind!r}")


def read_tree(group, like=None):
    """The tree :func:`write_tree` wrote into ``group``, with the same types. ``like`` (optional): a
    tree of the expected structure; the one read must have it, and its leaves take the dtypes and
    array kinds (numpy or jax) of ``like``'s (e.g. an optimiser state as ``opt.init`` makes it)."""
    tree = _read_node(group)
    if like is not None:
        tree = conform(tree, like)
    return tree


def _read_node(group):
    kind = group.attrs["__node__"]
    kind = kind.decode() if isinstance(kind, bytes) else str(kind)
    leaves = json.loads(group.attrs["__leaves__"])

    def child(name):
        return _read_leaf(group, name, leaves[name]) if name in leaves else _read_node(group[name])

    if kind in ("list", "tuple"):
        items = [child(str(i)) for i in range(int(group.attrs["__length__"]))]
        return items if kind == "list" else tuple(items)
    if kind == "dict":
        return {k: child(str(i)) for i, k in enumerate(json.loads(group.attrs["__keys__"]))}
    cls = _lookup(str(group.attrs["__type__"]))
    if kind == "namedtuple":
        if not (isinstance(cls, type) and issubclass(cls, tuple) and hasattr(cls, "_fields")):
            raise TreeError(f"{cls} is not a NamedTuple")
        return cls(*(child(n) for n in cls._fields))
    if kind == "dataclass":
        if not dataclasses.is_dataclass(cls):
            raise TreeError(f"{cls} is not a dataclass")
        fields = dataclasses.fields(cls)
        values = {}
        for f in fields:
            if f.name in leaves or f.name in group:
                values[f.name] = child(f.name)
            elif f.init and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise TreeError(f"{cls.__name__} lacks its field {f.name!r}")
            # else: a field written before it existed takes its default
        obj = cls(**{f.name: values[f.name] for f in fields if f.init and f.name in values})
        for f in fields:
            if not f.init and f.name in values:
                object.__setattr__(obj, f.name, values[f.name])
        return obj
    raise TreeError(f"unknown node kind {kind!r}")


def conform(tree, like):
    """``tree`` checked to have the structure of ``like`` (a :class:`TreeError` if not), its leaves
    given the dtypes and array kinds (numpy or jax) of ``like``'s."""
    import jax
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    want, want_def = jax.tree_util.tree_flatten(like)
    if treedef != want_def:
        raise TreeError(f"the structure read ({treedef}) is not the one expected ({want_def})")
    out = []
    for i, (a, b) in enumerate(zip(leaves, want)):
        if np.shape(a) != np.shape(b):
            raise TreeError(f"leaf {i} has shape {np.shape(a)}, expected {np.shape(b)}")
        if isinstance(b, jax.Array):
            out.append(jax.numpy.asarray(a, dtype=b.dtype))
        elif isinstance(b, (np.ndarray, np.generic)):
            out.append(np.asarray(a, dtype=b.dtype) if isinstance(b, np.ndarray) else b.dtype.type(a))
        else:
            out.append(a)
    return jax.tree_util.tree_unflatten(treedef, out)
