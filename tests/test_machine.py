"""neumat.machine: the machine line every benchmark prints beside its figures."""

import pytest

from neumat import machine

ZEN5 = """processor\t: 0
vendor_id\t: AuthenticAMD
cpu family\t: 26
model\t\t: 2
model name\t: AMD EPYC
flags\t\t: fpu sse2 avx2 avx512f
"""
ARM = """processor\t: 0
BogoMIPS\t: 50.00
Features\t: fp asimd
CPU implementer\t: 0x41
"""


@pytest.fixture
def cpuinfo(monkeypatch):
    def use(text):
        monkeypatch.setattr(machine, "_read_cpuinfo", lambda: text)
        for f in (machine.cpu_family, machine.cpu_model, machine.cpu_flags):
            f.cache_clear()
    yield use
    for f in (machine.cpu_family, machine.cpu_model, machine.cpu_flags):
        f.cache_clear()


def test_a_bare_model_name_gets_its_x86_family(cpuinfo, monkeypatch):
    """A hypervisor's "AMD EPYC" says neither Zen 4 nor Zen 5: the line adds family and model
    (the "model" line, not "model name")."""
    cpuinfo(ZEN5)
    monkeypatch.setattr(machine.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(machine.platform, "machine", lambda: "x86_64")
    assert machine.cpu_family() == "family 26 model 2"
    assert machine.describe() == "CPU AMD EPYC (x86_64 family 26 model 2, AVX-512, 2 CPUs)"


def test_no_family_where_cpuinfo_has_none(cpuinfo, monkeypatch):
    cpuinfo(ARM)
    monkeypatch.setattr(machine.os, "cpu_count", lambda: 4)
    monkeypatch.setattr(machine.platform, "machine", lambda: "aarch64")
    monkeypatch.setattr(machine.platform, "processor", lambda: "")
    assert machine.cpu_family() is None
    assert machine.describe() == "CPU aarch64 (aarch64, NEON, 4 CPUs)"
    cpuinfo("")
    assert machine.cpu_family() is None
