"""``python -m cmtool`` runs the command line."""

from cmtool.cli import main

main()
