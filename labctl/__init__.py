"""labctl: lab controller for moving-object recognition with premarking and active vision.

Rebuilds He, Hujic, Mills & Benhabib, "Moving-object recognition using premarking and
active vision" (ICRA 1996) as an installable lab controller. Nothing runs at import time.
"""

__version__ = "0.1.0"

import logging as _logging

# A library's loggers stay silent unless the application configures logging (`labctl -v` does; a
# run routes them to its record): never Python's last-resort stderr handler, which would break the
# one-line-per-failure contract with tracebacks.
_logging.getLogger("labctl").addHandler(_logging.NullHandler())
