"""Which recording of the demos a study's runs trained on: the dataset's fingerprint, kept and checked."""

import json
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from lerobot_pacdp.study import runner
from lerobot_pacdp.study.data import dataset_fingerprint
from lerobot_pacdp.study.presets import get_preset
from lerobot_pacdp.study.state import DATASET_FILE

FAKE_TRAINER = f"{sys.executable} {Path(__file__).with_name('fake_trainer.py')}"
PUSHT = get_preset("cpu").task("pusht")  # its dataset lives in <output_dir>/data/pusht
ACTIONS = np.arange(12, dtype=np.float32).reshape(6, 2) / 7


def _record(output_dir: Path, actions: np.ndarray, compression: str = "snappy") -> Path:
    """A LeRobot data file of one episode with these actions; returns the file."""
    flat = pa.array(actions.ravel())
    table = pa.table({"action": pa.FixedSizeListArray.from_arrays(flat, actions.shape[1]),
                      "episode_index": pa.array(np.zeros(len(actions), dtype=np.int64))})  # fmt: skip
    file = output_dir / "data" / "pusht" / "data" / "chunk-000" / "file-000.parquet"
    file.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, file, compression=compression)
    return file


def _one_ulp_up(actions: np.ndarray) -> np.ndarray:
    changed = actions.copy()
    changed[5, 1] = np.nextafter(changed[5, 1], np.float32(np.inf))
    return changed


def test_the_fingerprint_follows_the_values_down_to_the_last_bit_not_the_file_bytes(tmp_path):
    assert dataset_fingerprint(PUSHT, tmp_path) is None  # no dataset there
    file = _record(tmp_path, ACTIONS)
    first, first_bytes = dataset_fingerprint(PUSHT, tmp_path), file.read_bytes()
    _record(tmp_path, ACTIONS, compression="none")
    assert file.read_bytes() != first_bytes and dataset_fingerprint(PUSHT, tmp_path) == first
    _record(tmp_path, _one_ulp_up(ACTIONS))
    assert dataset_fingerprint(PUSHT, tmp_path) != first


def test_a_run_is_refused_through_the_cli_once_its_demos_were_recorded_again(tmp_path, capsys):
    info = tmp_path / "data" / "pusht" / "meta" / "info.json"
    info.parent.mkdir(parents=True)
    info.write_text(json.dumps({"total_episodes": 206}))
    _record(tmp_path, ACTIONS)
    argv = ["--preset=cpu", f"--output_dir={tmp_path}", "--seeds=[0]", "--demos=[20]", "--methods=[DP]",
            "--steps=4", "--save_freq=2", "--metrics=false", f"--trainer={FAKE_TRAINER}"]  # fmt: skip
    assert runner.main(argv) == 0
    (run_dir,) = (tmp_path / "runs" / "pusht" / "main").iterdir()
    kept = json.loads((run_dir / DATASET_FILE).read_text())
    assert kept == {"fingerprint": dataset_fingerprint(PUSHT, tmp_path)}
    _record(tmp_path, _one_ulp_up(ACTIONS))
    capsys.readouterr()
    assert runner.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("pacdp-study: error: ") and len(err.splitlines()) == 1
    assert f"started on another recording of the pusht demos than the one in {tmp_path} now" in err
    assert json.loads((run_dir / DATASET_FILE).read_text()) == kept  # still the recording it started on
