"""`python -m relocfw` runs the CLI, like the `relocfw` command."""

from relocfw.app.cli import main

main()
