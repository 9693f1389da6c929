"""``python -m gctr_cli``: the same as the ``gctr`` command."""

from gctr_cli.cli import run

if __name__ == "__main__":
    run()
