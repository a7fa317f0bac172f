"""Where the tests find things: the repository root, whatever the working
directory, and the scenes shared beside it."""
from __future__ import annotations

import os

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
# Scenes shared between projects sit beside the checkout (../shared/scenes),
# not inside it: a clone elsewhere has none, and the tests reading them skip.
SHARED = os.path.normpath(os.path.join(REPO, "..", "shared"))
SHARED_SCENES = os.path.join(SHARED, "scenes")
needs_shared_scenes = pytest.mark.skipif(not os.path.isdir(SHARED_SCENES),
                                         reason="../shared/scenes (beside the checkout) absent")
