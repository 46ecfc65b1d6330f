"""The ``diffaccel`` command-line tool: one click group, commands in sibling modules."""

from __future__ import annotations

import logging

import click

from diffaccel import __version__


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="diffaccel")
@click.option(
    "-v", "--verbose", count=True, help="More log output (-v info, -vv debug)."
)
def main(verbose: int) -> None:
    """Differentiable modeling of particle accelerators."""
    level = logging.WARNING - 10 * min(verbose, 2)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")


# Commands register themselves below (one module per command family).
from diffaccel.cli.synthetic import synthetic  # noqa: E402

main.add_command(synthetic)

from diffaccel.cli.hysteresis import hysteresis  # noqa: E402

main.add_command(hysteresis)

from diffaccel.cli.hysteresis_gp import gp_fit  # noqa: E402

hysteresis.add_command(gp_fit)

from diffaccel.cli.reconstruct import predict, reconstruct_command  # noqa: E402

main.add_command(reconstruct_command)
main.add_command(predict)

from diffaccel.cli.demo import demo  # noqa: E402

main.add_command(demo)
