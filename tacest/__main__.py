"""``python -m tacest`` runs the command line."""

from tacest.cli.main import main

main()
