"""The scene format (docs/formats.md §2).

- :mod:`jaxplush.scene.parse`: reads and validates scene files into a :class:`Scene` (numpy data,
  never traced); errors name the file and line.
- :mod:`jaxplush.scene.write`: writes scenes back in the same format.
"""
