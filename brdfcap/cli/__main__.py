"""``python -m brdfcap.cli``: the same as the ``brdfcap`` console script."""

from brdfcap.cli import entry

entry()
