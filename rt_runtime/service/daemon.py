"""Entry point of ``excavator-rtd``, the systemd service that runs trench jobs on the rig PC.

The console script is declared with the package so that installs and unit files can name it;
the daemon itself (config, CAN boot, job store, control socket) is built with the executor.
Until then the entry point refuses to start, with a non-zero exit, rather than pretend to run.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence


def main(argv: Sequence[str] | None = None) -> int:
    """Refuse to start: the daemon is not part of this release yet."""
    del argv
    print(
        "excavator-rtd: the rig daemon is not available in this release; "
        "use `excavator-rt` for planning and simulation",
        file=sys.stderr,
    )
    return 3


if __name__ == "__main__":
    sys.exit(main())
