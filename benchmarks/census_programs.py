"""Which simulator programs a test run builds, and how many would remain if parts of the scene were data.

A pytest plugin and its report. Every single-scene program built through
:func:`jaxplush.stepping.compiled.get` and every batched simulator asked for is written, one JSON
line each, with the key it has today and the keys it would have with the topology, the sizes or
dt passed as data:

    PYTHONPATH=benchmarks CENSUS_OUT=/tmp/census/out python -m pytest -q -p census_programs
    python benchmarks/census_programs.py /tmp/census/out

(one file per process: ``out.<pid>``). Nothing of jaxplush is changed: the plugin wraps
``compiled.get`` and ``batched.shared_simulator``.
"""

from __future__ import annotations

import glob
import hashlib
import json
import os
import re
import sys

import numpy as np


def _connectivity(scene):
    """A digest of the scene without its vertex positions (what a program keyed on topology would see)."""
    h = hashlib.sha1()
    a = np.ascontiguousarray(scene.faces)
    h.update(repr((a.dtype.str, a.shape)).encode())
    h.update(a.tobytes())
    h.update(repr((len(scene.vertices), tuple((o.vertex_slice, o.face_slice, tuple(o.fixed), o.has_gas)
                                              for o in scene.objects),
                   tuple(np.asarray(scene.gravity, np.float64).tolist()), scene.floor, scene.temperature,
                   scene.floor_friction, scene.floor_restitution, scene.contact, scene.self_collision,
                   scene.contact_capacity, scene.contact_friction, scene.floor_model, bool(scene.driven))).encode())
    return h.hexdigest()[:12]


_OUT = [None]


def pytest_unconfigure(config):
    if _OUT[0] is not None:
        _OUT[0].close()


def pytest_configure(config):
    from jaxplush.stepping import batched, compiled
    out = _OUT[0] = open(os.environ.get("CENSUS_OUT", "/tmp/census/out") + f".{os.getpid()}", "a")
    get, shared = compiled.get, batched.shared_simulator

    def write(**row):
        out.write(json.dumps(row) + "\n")
        out.flush()

    def counted_get(sim, name, build):
        entry = compiled._CACHE.get(sim)
        if entry is None or name not in entry:
            sc = sim.scene
            write(kind="single", name=repr(name), fp=sim.key[0][:12], conn=_connectivity(sc),
                  size=[len(sc.vertices), len(sc.faces), len(sc.objects)], rest=repr(sim.key[1:]))
        return get(sim, name, build)

    def counted_shared(scene, dt, batch, terms, substeps=1, chunk=None):
        write(kind="batched", name="batched", fp=scene.fingerprint[:12], conn=_connectivity(scene),
              size=[len(scene.vertices), len(scene.faces), len(scene.objects)],
              rest=repr((float(dt), batch, terms, substeps, chunk)))
        return shared(scene, dt, batch, terms, substeps, chunk)

    compiled.get = counted_get
    batched.shared_simulator = counted_shared


def report(prefix):
    rows = [json.loads(line) for f in glob.glob(prefix + ".*") for line in open(f)]

    def no_dt(r):
        return re.sub(r"^\(([^,]+),", "(", r["rest"])
    keys = {
        "as today": lambda r: (r["name"], r["fp"], r["rest"]),
        "topology as data, exact sizes": lambda r: (r["name"], r["conn"], r["rest"]),
        "one bucket for every size": lambda r: (r["name"], r["rest"]),
        "one bucket, dt as data": lambda r: (r["name"], no_dt(r)),
    }
    print("| programs | " + " | ".join(keys) + " |")
    print("|---|" + "---:|" * len(keys))
    for kind, sel in (("single-scene (all)", lambda r: r["kind"] == "single"),
                      ("rollouts", lambda r: r["name"] == "'rollout'"),
                      ("starts", lambda r: r["name"] == "'init'"),
                      ("batched simulators", lambda r: r["kind"] == "batched")):
        rs = [r for r in rows if sel(r)]
        print(f"| {kind} | " + " | ".join(str(len({k(r) for r in rs})) for k in keys.values()) + " |")


if __name__ == "__main__":
    report(sys.argv[1] if len(sys.argv) > 1 else "/tmp/census/out")
