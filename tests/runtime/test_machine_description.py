"""What a benchmark records of its machine: the CPU's model and flags read from Linux's /proc/cpuinfo, one parser
for the runtime's benchmark and the trainer's choice of a bf16 step."""

from __future__ import annotations

from popcode_runtime.inference.benchmark import CPU_FLAGS, machine_description, parse_cpuinfo

X86 = """processor\t: 0
vendor_id\t: AuthenticAMD
model name\t: AMD EPYC 9R14
flags\t\t: fpu sse2 avx2 fma avx512f avx512_bf16
processor\t: 1
model name\t: another core
flags\t\t: fpu
"""
ARM = """processor\t: 0
BogoMIPS\t: 50.00
Features\t: fp asimd evtstrm aes
"""


def test_the_first_processor_gives_model_and_flags() -> None:
    model, flags = parse_cpuinfo(X86.splitlines())
    assert model == "AMD EPYC 9R14"
    assert flags == {"fpu", "sse2", "avx2", "fma", "avx512f", "avx512_bf16"}


def test_arm_lists_its_features_and_no_model_name() -> None:
    model, flags = parse_cpuinfo(ARM.splitlines())
    assert model is None
    assert "asimd" in flags and "fp" in flags


def test_nothing_to_read_gives_no_model_and_no_flags() -> None:
    assert parse_cpuinfo([]) == (None, frozenset())


def test_the_description_keeps_only_the_flags_that_change_speed() -> None:
    description = machine_description()
    assert set(description["cpu_flags"]) <= set(CPU_FLAGS)
    assert description["cores"] >= 1 and description["cpu"]
