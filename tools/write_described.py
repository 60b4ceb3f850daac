"""Write geoortho/processing/described.json: the registry's functions as read from their sources,
ready-made for a quick start-up. Run it after changing a core function's signature or docstring
(tests/test_api.py says when it is stale)."""

from geoortho.processing.algorithms import ALGORITHMS
from geoortho.processing.static import READY_MADE, ready_made_text

READY_MADE.write_text(ready_made_text([a.function_ref for a in ALGORITHMS]))
print(f"wrote {READY_MADE}")
