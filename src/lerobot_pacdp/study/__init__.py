"""The DP vs BDP vs PAC-DP reproduction study (paper Sec. IV), `pacdp-study`.

Data flows one way: `presets` (the numbers) -> `plan` (runs, episodes, train configs) -> `state` (where
each run stands, from its directory) -> `data` (datasets), `executors` / `slurm` (where runs train) ->
`evaluation` (metrics of the runs) -> `tables` (reports); `runner` is the CLI.
"""
