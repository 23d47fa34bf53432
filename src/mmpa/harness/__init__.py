"""The experiment harness: the runner (config, seeds, output folders, reports), the executor
(local processes or Ray), sweeps, plots, and the twin site the experiments and apps share."""
