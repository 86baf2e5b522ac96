"""The CPU's flags, read from /proc/cpuinfo's text."""
from tracker.core.cpu import cpu_flags, int8_vnni

CPUINFO = "processor\t: 0\nflags\t\t: fpu sse2 avx2 {}\nbogomips\t: 4000\nprocessor\t: 1\nflags\t\t: fpu\n"


def test_the_flags_are_the_union_of_the_flags_lines():
    assert cpu_flags(CPUINFO.format("avx512f")) == {"fpu", "sse2", "avx2", "avx512f"}
    assert cpu_flags("") == set()


def test_int8_dot_products_need_vnni_or_amx():
    assert int8_vnni(CPUINFO.format("avx512_vnni"))
    assert int8_vnni(CPUINFO.format("avx_vnni"))
    assert int8_vnni(CPUINFO.format("amx_int8 amx_tile"))
    assert not int8_vnni(CPUINFO.format("avx512f avx512bw"))
