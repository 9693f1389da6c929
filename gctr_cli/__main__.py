"""``python -m gctr_cli``: the same as the ``gctr`` command."""

from gctr_cli.cli import main

if __name__ == "__main__":
    main(prog_name="gctr")
