"""robomimic support (Lift, Can, Square, Transport, ToolHang; state-based) for PAC-DP.

- `tasks`: the task table (robosuite names, budgets, observation layouts, paper settings).
- `hdf5_adapter`: robomimic hdf5 -> LeRobotDataset v3 (`pacdp-convert-robomimic`).
- `env` / `env_config`: a gymnasium env on robosuite 1.5 and `--env.type=robomimic` for lerobot-eval.
- `compat`: translating robosuite <= 1.4 recordings (the released files) to robosuite 1.5.
- `scripted_experts`: scripted Lift/Can/Square demonstrations in robomimic format (`pacdp-scripted-demos`).

Importing this package imports nothing heavy; robosuite is imported when an environment is built.
"""
