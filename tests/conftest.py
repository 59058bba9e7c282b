"""Test-session set-up.

torch and numba each load an OpenMP runtime whose idle threads spin; on two cores they spin
against each other's work (see ``plenoctree.runtime``). The CLI sets ``OMP_WAIT_POLICY=PASSIVE``
before either loads; tests import torch before calling the CLI in-process, so the policy is
set here, before either runtime is loaded (``./run test`` also exports it).
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
