"""Plugin discovery: valid plugins load, broken or mistyped ones are skipped with a warning."""

import importlib.metadata
import sys
import types

import pytest

from nerfpipe.util.registry import ADAPTER_GROUP, AdapterSpec, PluginWarning, discover

GOOD = AdapterSpec(name="fake", description="a fake format", detect=lambda p: 0, read=lambda p: None)


@pytest.fixture
def fake_entry_points(monkeypatch):
    mod = types.ModuleType("nerfpipe_fake_plugin")
    mod.GOOD, mod.WRONG = GOOD, "not a spec"
    monkeypatch.setitem(sys.modules, "nerfpipe_fake_plugin", mod)
    eps = [
        importlib.metadata.EntryPoint("fake", "nerfpipe_fake_plugin:GOOD", ADAPTER_GROUP),
        importlib.metadata.EntryPoint("wrong", "nerfpipe_fake_plugin:WRONG", ADAPTER_GROUP),
        importlib.metadata.EntryPoint("broken", "nerfpipe_no_such_module:X", ADAPTER_GROUP),
        importlib.metadata.EntryPoint("fake", "nerfpipe_fake_plugin:GOOD", ADAPTER_GROUP),
    ]
    monkeypatch.setattr(importlib.metadata, "entry_points", lambda group=None: [e for e in eps if e.group == group])


def test_discover_validates_and_warns(fake_entry_points):
    with pytest.warns(PluginWarning) as record:
        found = discover(ADAPTER_GROUP, AdapterSpec)
    assert found == {"fake": GOOD}
    text = " ".join(str(w.message) for w in record)
    assert "'wrong'" in text and "not a AdapterSpec" in text
    assert "'broken'" in text and "failed to load" in text
    assert "registered twice" in text


def test_builtin_adapters_register_through_entry_points():
    names = {ep.name for ep in importlib.metadata.entry_points(group=ADAPTER_GROUP)}
    assert {"npz", "transforms", "colmap"} <= names
