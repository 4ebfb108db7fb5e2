"""``python -m sliscan``: the same as the ``sliscan`` command."""

from sliscan.cli import main

main()
