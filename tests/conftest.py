import os
import sys
from pathlib import Path

import torch

# Tests run on two cores, in as many pytest-xdist workers as `make test` starts: keep torch from oversubscribing.
_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
torch.set_num_threads(max(1, min(2, (os.cpu_count() or 1) // _WORKERS)))
sys.path.insert(0, str(Path(__file__).parent))
