"""The core: plugin interfaces, values, the Relocalizer pipeline and its helpers.

Plain Python + torch; imports nothing from relocfw's other parts, so a plugin or a
robot-side script needs only this.
"""
