"""Short modules: none in kernels/ or service/ over 600 lines (one concept per file)."""
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIMIT = 600


def test_no_module_in_kernels_or_service_is_over_600_lines():
    long = {str(p.relative_to(ROOT)): n for folder in ("kernels", "service") for p in (ROOT / folder).rglob("*.py")
            if (n := len(p.read_text().splitlines())) > LIMIT}
    assert not long, f"modules over {LIMIT} lines (split them by concern): {long}"
