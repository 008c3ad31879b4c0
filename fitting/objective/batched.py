"""The batched engine moved to :mod:`jaxplush.stepping.batched` (the core); this name stays so
that code written against ``jaxplush.fitting.objective.batched`` keeps working: it is that module."""

import sys

from jaxplush.stepping import batched as _batched

sys.modules[__name__] = _batched
