"""Test-session set-up.

torch and numba each load an OpenMP runtime whose idle threads spin; on two cores they spin
against each other's work (see ``plenoctree.nerf.trainer.RUNTIME_ENV``). The CLI re-executes
itself with ``OMP_WAIT_POLICY=PASSIVE``; tests call the CLI in-process, so the policy is set
here, before either runtime is loaded (``./run test`` also exports it).
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
