"""Entry point for ``python -m diffaccel``."""

from diffaccel.cli.main import run

if __name__ == "__main__":
    run()
