"""The model: static topology and the physical terms (docs/model.md §1, §6, §7).

- :mod:`jaxplush.model.mesh`: mesh checks and orientation (numpy).
- :mod:`jaxplush.model.forces`: topology, ``Terms`` (what a program compiles in), the spring,
  gas, dashpot and drag forces, the smooth floor, energies.
- :mod:`jaxplush.model.contact`: soft-soft contact and self-collision: candidate lists, the
  penalty force, overflow flags.
"""
