"""The DP vs BDP vs PAC-DP reproduction study (paper Sec. IV): presets, a resumable runner, tables and plots."""
