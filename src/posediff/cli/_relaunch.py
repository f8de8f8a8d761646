"""The script Lightning's DDP launcher runs for ranks > 0.

Lightning starts the other ranks by re-executing ``sys.argv`` (a file path plus the Hydra
overrides). ``posediff <command>`` points ``sys.argv[0]`` here and names the command in
``POSEDIFF_COMMAND``, so each rank runs the same command with the same overrides.
"""

import os
import sys

if __name__ == "__main__":
    from posediff.cli import main

    sys.exit(main([*os.environ["POSEDIFF_COMMAND"].split(), *sys.argv[1:]]))
