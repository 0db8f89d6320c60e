"""The core: plugin interfaces, values, the Relocalizer pipeline and its helpers.

Imports nothing from relocfw's other parts (tests/core/test_layout.py checks it): a plugin
builds on this part alone.
"""
