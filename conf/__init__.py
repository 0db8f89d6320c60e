"""relocfw's Hydra config groups (installed as relocfw.conf).

config.yaml's defaults list starts with the schema of its types, which lives in Python
(relocfw.app.config_schema): it is registered here, where Hydra reads this package, so
every composition of relocfw.conf finds it (the CLI's, and `hydra.compose` in a script).
"""

from relocfw.app.config_schema import store

store()
