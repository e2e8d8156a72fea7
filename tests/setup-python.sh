#!/usr/bin/env bash
# Creates .venv with the independent checkers the integration tests call (KLayout's Python
# module reads our GDSII back, trimesh checks our STL, OpenEXR and colour-science check our
# EXR reading), pytest, and this checkout's Python module `doefab` installed by `pip install .`
# as a user installs it (rebuilt each time, so that it follows the sources). Idempotent.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
fi
if ! .venv/bin/python -c "import klayout.db, trimesh, numpy, OpenEXR, colour, cv2, scipy, pytest" 2>/dev/null; then
  .venv/bin/pip install --quiet --disable-pip-version-check -r tests/requirements.txt
fi
.venv/bin/pip install --quiet --disable-pip-version-check .
