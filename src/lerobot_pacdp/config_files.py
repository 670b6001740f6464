"""The lerobot-train `--config_path` files shipped with the package (the checkout's `configs/` links here).

They are package data, so an installed package (not only an editable checkout) finds them.
"""

import json
from pathlib import Path

from lerobot_pacdp.cli_errors import UserInputError

CONFIGS_DIR = Path(__file__).parent / "configs"


def config_file(name: str) -> Path:
    """The path of a shipped config file, e.g. `config_file("pusht/pacdp_cpu.json")`."""
    path = CONFIGS_DIR / name
    if not path.is_file():
        raise UserInputError(f"{path} is missing from the installed package; reinstall lerobot_policy_pacdp.")
    return path


def load_config_file(name: str) -> dict:
    """A shipped config file's content (a lerobot-train config as a dict)."""
    return json.loads(config_file(name).read_text())
