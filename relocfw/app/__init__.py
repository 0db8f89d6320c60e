"""The application: the Hydra CLI (relocfw.app.cli, a table of tasks), the config's
types (config_schema) and old spellings (spellings), one module per task
(relocfw.app.tasks), plugin discovery and the torchrun entry. Hydra and OmegaConf are
seen here only."""
