"""The plugin API only grows (docs/plugins.md, "Versioning").

tests/api_surface.json records relocfw's public names, the three interfaces' public
members with their signatures and the value types' fields. A removed name, member or
field, or a changed signature, fails here; additions pass. After a deliberate
addition, record it:

    .venv/bin/python tests/core/test_api_surface.py --write
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import sys
from pathlib import Path

import relocfw

RECORD = Path(__file__).with_name("api_surface.json")
INTERFACES = ("Backbone", "SimilarityIndex", "CropSearch", "CropDistance", "PoseRefiner")
VALUES = ("Crop", "Pose", "PoseOutput", "Localization", "MapImage", "RefineQuery", "Refined")


def member_description(member: object) -> str:
    """A public member as a plugin sees it: a signature, or the kind of value."""
    function = member.__func__ if isinstance(member, (classmethod, staticmethod)) else member
    if isinstance(function, property):
        return "property"
    if callable(function):
        return f"{type(member).__name__}{inspect.signature(function)}"
    return f"attribute {type(member).__name__}"


def surface() -> dict:
    interfaces = {
        name: {
            member: member_description(value)
            for member, value in vars(getattr(relocfw, name)).items()
            if not member.startswith("_")
        }
        for name in INTERFACES
    }
    values = {name: [f.name for f in dataclasses.fields(getattr(relocfw, name))] for name in VALUES}
    return {"all": sorted(relocfw.__all__), "interfaces": interfaces, "values": values}


def lost(recorded: dict, now: dict) -> list[str]:
    """What `now` no longer has of `recorded`, or has changed."""
    problems = [f"relocfw.{name} removed" for name in recorded["all"] if name not in now["all"]]
    for name, members in recorded["interfaces"].items():
        current = now["interfaces"].get(name, {})
        for member, description in members.items():
            if member not in current:
                problems.append(f"{name}.{member} removed")
            elif current[member] != description:
                problems.append(f"{name}.{member} changed: {description} -> {current[member]}")
    for name, fields in recorded["values"].items():
        current = now["values"].get(name, [])
        if current[: len(fields)] != fields:
            # Positional construction depends on the order of the recorded fields.
            problems.append(f"{name} fields {fields} became {current}")
    return problems


def test_the_plugin_api_only_grows():
    problems = lost(json.loads(RECORD.read_text()), surface())
    assert not problems, (
        "the plugin API lost or changed: "
        + "; ".join(problems)
        + " (a breaking change bumps the major version, see docs/plugins.md)"
    )


def test_the_check_sees_a_removal_and_a_changed_signature():
    recorded = surface()
    now = json.loads(json.dumps(recorded))
    del now["interfaces"]["SimilarityIndex"]["fit"]
    now["interfaces"]["CropSearch"]["search"] = "function(self, width)"
    now["values"]["Crop"] = ["y", "x", "size"]
    now["all"].remove("Relocalizer")
    assert len(lost(recorded, now)) == 4
    now = json.loads(json.dumps(recorded))
    now["interfaces"]["CropSearch"]["new_hook"] = "function(self)"
    now["values"]["Pose"].append("covariance")
    assert lost(recorded, now) == []  # additions are allowed


if __name__ == "__main__" and sys.argv[1:] == ["--write"]:
    RECORD.write_text(json.dumps(surface(), indent=2, sort_keys=True) + "\n")
    print(f"written: {RECORD}")
