"""`python -m stitchplan` runs the command line, exactly as the `stitchplan` command does."""

from .cli import main

if __name__ == "__main__":
    main()
