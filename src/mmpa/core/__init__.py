"""The core every layer stands on: SE(2)/SE(3) geometry, the exception hierarchy, config
loading (pydantic + YAML + ``--set``), YAML I/O and logging. Imports numpy and pydantic only."""
