import os

import warp as wp

wp.config.quiet = True
# Warp's CPU backend runs each kernel on one thread: tests keep scenes to a few thousand particles.
DEVICE = os.environ.get("ROCKWAVE_TEST_DEVICE", "cpu")
