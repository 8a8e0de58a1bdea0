"""Subcommands of ``appliance``, one module each, discovered automatically.

A command module defines ``NAME`` (str), ``HELP`` (one line), ``add_arguments(parser)`` and
``run(args) -> int``. Keep imports of heavy modules inside ``run`` so ``appliance --help`` is quick.
"""
