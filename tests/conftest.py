import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import os
import tempfile

# every test run gets its own state directory (persisted calibration, alarm states, ...), shared with the
# processes the tests start
os.environ.setdefault("MAGMESH_STATE_DIR", tempfile.mkdtemp(prefix="magmesh-test-state-"))
