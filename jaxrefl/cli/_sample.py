"""Placeholder: this command is being written; replaced by its implementation."""

import argparse

HELP = "posterior sampling (in progress)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", nargs="?")


def run(args: argparse.Namespace) -> int:
    raise ValueError("this command is not available yet")
