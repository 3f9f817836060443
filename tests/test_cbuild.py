"""The C kernels build wherever a compiler exists. A kernel that fails to compile is logged and
the torch path serves instead, so its own tests skip as on a machine without a compiler: this
test is what turns a broken C file into a failure rather than a green run of skips."""
import os
import shutil

import pytest


def test_every_c_kernel_builds_where_a_compiler_exists():
    if shutil.which(os.environ.get("CC", "cc")) is None:
        pytest.skip("no C compiler: every kernel falls back to torch by design")
    from neumat import fit_kernel
    from neumat.btf import query
    from neumat.btf.synthesis import kernel
    from neumat.metrics import distances
    assert fit_kernel.available(), "fit_step.c did not build (its log names the compiler error)"
    assert query.available(), "btf/query_kernel.c did not build"
    assert distances._l1_library() is not None, "metrics/l1_kernel.c did not build"
    assert distances._ssim_library() is not None, "metrics/ssim_kernel.c did not build"
    if os.environ.get("NEUMAT_HPB_KERNEL", "1") != "0":
        assert kernel.available(), "the HPB features kernel (query_kernel.c) did not build"
