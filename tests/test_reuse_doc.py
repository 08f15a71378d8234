"""docs/reuse.md is run: its python blocks, in order, put SR-DCIL on the page's own point env and
must learn the goal chain."""
import re
from pathlib import Path

import pytest

PAGE = Path(__file__).resolve().parents[1] / "docs" / "reuse.md"


def page_code() -> str:
    # ```python blocks are run; ```py blocks (a trained policy file) are illustrations
    return "\n\n".join(re.findall(r"```python\n(.*?)```", PAGE.read_text(), flags=re.S))


def test_the_page_has_the_pieces():
    code = page_code()
    for piece in ("GoalSequenceTransform(", "MixedReplay(", "DCILSACLoss(", "Collector(", "evaluate_chain(",
                  "check_env_specs(", "extract_goals(", "Demonstration("):
        assert piece in code, piece
    loop = code[code.index("collector = Collector("):code.index('print("chain solved"')]
    assert len(loop.strip().splitlines()) <= 40


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_the_page_runs_and_learns_the_chain(capsys):
    ns: dict = {"__name__": "reuse_doc"}
    exec(compile(page_code(), str(PAGE), "exec"), ns)
    m = ns["metrics"]
    out = capsys.readouterr().out
    assert m["chain_success"] == 1.0 and m["goals_reached"] == len(ns["goals"]), out[-2000:]
    assert ns["frames"] < ns["TOTAL_FRAMES"]
