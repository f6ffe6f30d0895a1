"""Write tests/compile_budget.json from the programs each module built in the
last ``make test`` (``.test-logs/compilations.tsv``), with a quarter more
(at least 10) as headroom: ``python tests/compile_budget.py``."""

import json
import math
from pathlib import Path

root = Path(__file__).resolve().parent
rows = [line.split("\t") for line in (root.parent / ".test-logs" / "compilations.tsv").read_text().splitlines()]
# A quarter more, and at least 10 more: the property tests' count moves with
# hypothesis's draws (20 to 28 programs in three runs).
budget = {name: max(math.ceil(int(count) * 1.25), int(count) + 10) for name, count, *_ in rows}
(root / "compile_budget.json").write_text(json.dumps(dict(sorted(budget.items())), indent=1) + "\n")
print(f"wrote {len(budget)} budgets to {root / 'compile_budget.json'}")
