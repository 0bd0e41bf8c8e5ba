"""``calendaring`` with one injected fault, for tests/system/test_faults.py.

    python -m tests.system.faultinject FUNCTION CALL ARGV...

runs ``calendaring ARGV...`` in which the CALL-th call of ``calendaring.process.runfile.FUNCTION``
(``write_checkpoint`` or ``write_run``) hits a full disk part-way through: the HDF5 file is
open and partly written when the ENOSPC error comes, as on a real full disk.
"""

from __future__ import annotations

import errno
import sys

from calendaring.process import runfile


def full_disk(name: str, on_call: int) -> None:
    real = getattr(runfile, name)
    real_put, real_dataset = runfile._put, runfile._dataset
    calls = {"n": 0}

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    def flaky(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] != on_call:
            return real(*args, **kwargs)
        runfile._put, runfile._dataset = full, full
        try:
            return real(*args, **kwargs)
        finally:
            runfile._put, runfile._dataset = real_put, real_dataset

    setattr(runfile, name, flaky)


if __name__ == "__main__":
    full_disk(sys.argv[1], int(sys.argv[2]))
    from calendaring.cli import main

    sys.exit(main(sys.argv[3:]))
