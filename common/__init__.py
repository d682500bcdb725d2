"""What every package may use: strict JSON configs, atomic files and directories, training state, CLI helpers."""
