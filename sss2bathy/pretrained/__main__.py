"""``python -m sss2bathy.pretrained export|show ...`` (:func:`sss2bathy.pretrained.main`)."""

import sys

from sss2bathy.pretrained import main

sys.exit(main())
