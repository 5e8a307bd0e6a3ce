"""The ``gra-mi`` command line: parse, validate, call one library function per command (:mod:`gra_mi.cli.main`)."""

from gra_mi.cli.main import COMMANDS, build_parser, main

__all__ = ["COMMANDS", "build_parser", "main"]
