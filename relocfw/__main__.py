"""`python -m relocfw` runs the CLI, like the `relocfw` command."""

from relocfw.cli import main

main()
