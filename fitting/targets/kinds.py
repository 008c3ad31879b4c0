"""The kinds of target (:mod:`jaxplush.io.kinds`, where they are defined: the viewer in the core
reads targets too); the names the fitting modules use."""

from jaxplush.io.kinds import KINDS, Kind, Mixed, Points, Positions, TargetKind, Tracks, kind, row_weight  # noqa: F401
