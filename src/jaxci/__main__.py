"""`python -m jaxci ...` is the `jaxci` command."""

from .cli import entry

entry()
