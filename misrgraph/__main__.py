"""``python -m misrgraph``: the same command line as the ``misrgraph`` script."""

from __future__ import annotations

from misrgraph.commands.cli import main

__all__ = ["main"]

if __name__ == "__main__":
    main()
