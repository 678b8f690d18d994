"""`python -m nasa`: the same command line as `nasa`."""

from nasa.cli import main

main()
