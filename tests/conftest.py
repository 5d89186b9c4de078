import os

# Keep the Warp kernel cache inside the checkout (CI starts from a clean clone).
os.environ.setdefault("WARP_CACHE_PATH", os.path.join(os.path.dirname(os.path.dirname(__file__)), ".warp_cache"))

import torch

# As the stage CLIs do (stages.cli.single_threaded_torch): the tracer owns the cores.
torch.set_num_threads(1)
