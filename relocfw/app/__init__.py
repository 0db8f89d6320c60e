"""The application: the Hydra CLI (the only place that sees a config), its tasks as
plain functions, plugin discovery and the torchrun entry."""
