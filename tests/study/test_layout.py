"""The study's modules pass data one way (issue 15): each imports only the modules before it, nothing imports
the CLI, and the metrics and lerobot-train run directories know nothing of the study."""

import ast
from pathlib import Path

import lerobot_pacdp

PACKAGE = Path(lerobot_pacdp.__file__).parent
ORDER = ["presets", "plan", "state", "data", "executors", "slurm", "evaluation", "evidence", "overview", "tables", "runner"]


def _imported(path: Path) -> set[str]:
    """Every `lerobot_pacdp...` module the file imports, at module level or inside functions."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("lerobot_pacdp"):
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
        elif isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names if alias.name.startswith("lerobot_pacdp"))
    return names


def test_each_study_module_imports_only_the_modules_before_it():
    assert sorted(p.stem for p in (PACKAGE / "study").glob("*.py") if p.stem != "__init__") == sorted(ORDER)
    for index, name in enumerate(ORDER):
        study_imports = {m.split(".")[2] for m in _imported(PACKAGE / "study" / f"{name}.py")
                         if m.startswith("lerobot_pacdp.study.") and m.split(".")[2] in ORDER}  # fmt: skip
        assert study_imports <= set(ORDER[:index]), (name, study_imports - set(ORDER[:index]))


def test_nothing_outside_the_study_imports_it():
    for path in PACKAGE.rglob("*.py"):
        if "study" not in path.relative_to(PACKAGE).parts:
            assert not any(m.startswith("lerobot_pacdp.study") for m in _imported(path)), path
    assert not any(m.startswith(("lerobot_pacdp.metrics", "lerobot_pacdp.study")) for m in _imported(PACKAGE / "train_runs.py"))
