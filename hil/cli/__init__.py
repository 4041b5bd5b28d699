"""The ``hil`` command line: argparse only, one module per command group (``register``)."""
