"""Entry point for ``python -m diffaccel``."""

from diffaccel.cli.main import main

if __name__ == "__main__":
    main()
