"""``python -m labctl``: the labctl command line."""

from labctl.cli import main

main()
