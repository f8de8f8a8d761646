"""``python -m posediff.cli``: the ``posediff`` command."""

from .main import entrypoint

if __name__ == "__main__":
    entrypoint()
