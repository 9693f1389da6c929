"""The GCTR registration engine. Public entry point: :func:`register`."""

from gctr_cli.engine.gctr import register, score_transform
from gctr_cli.engine.result import RegistrationResult

__all__ = ["RegistrationResult", "register", "score_transform"]
