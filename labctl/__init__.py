"""labctl: lab controller for moving-object recognition with premarking and active vision.

Rebuilds He, Hujic, Mills & Benhabib, "Moving-object recognition using premarking and
active vision" (ICRA 1996) as an installable lab controller. Nothing runs at import time.
"""

__version__ = "0.1.0"
