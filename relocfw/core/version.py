"""relocfw's version, in one place below every part that records it in its outputs."""

VERSION = "0.1.0"
