import os

# Keep the Warp kernel cache inside the checkout (CI starts from a clean clone).
os.environ.setdefault("WARP_CACHE_PATH", os.path.join(os.path.dirname(os.path.dirname(__file__)), ".warp_cache"))
