"""C export: compiled with the system cc, loaded with ctypes, equal to the Python law."""

from __future__ import annotations

import ctypes
import subprocess

import numpy as np
import pytest

from hil.controllers.servo.empc import relative_map
from hil.controllers.servo.empc_export import c_source, write_c
from hil.controllers.servo.empc_tree import NOT_FOUND, OUTSIDE_BOX
from hil.controllers.servo.mpc import MpcConfig
from hil.errors import HilError
from tests.controllers.servo.test_mpqp import region_samples

pytestmark = [pytest.mark.slow]  # compiles the exported C

CASES = {
    "paper": MpcConfig(ht=3, hu=3, hp=50, ert="foh"),
    "zoh_12A": MpcConfig(ht=2, hu=2, hp=30, ert="zoh", u_min=-12000.0, u_max=12000.0),
}
SENTINEL = 1234.5


@pytest.fixture(scope="module", params=list(CASES))
def compiled(request, tmp_path_factory, explicit_law):
    law = explicit_law(CASES[request.param])
    folder = tmp_path_factory.mktemp(request.param)
    source = write_c(law, folder / "empc_law.c")
    obj = folder / "empc_law.o"
    lib = folder / "empc_law.so"
    subprocess.run(["cc", "-std=c99", "-pedantic", "-Wall", "-Wextra", "-Werror", "-O2",
                    "-fPIC", "-c", str(source), "-o", str(obj)], check=True)
    subprocess.run(["cc", "-shared", str(obj), "-o", str(lib)], check=True)
    dll = ctypes.CDLL(str(lib))
    dll.empc_eval.restype = ctypes.c_int
    dll.empc_eval.argtypes = [ctypes.POINTER(ctypes.c_double), ctypes.POINTER(ctypes.c_double)]
    return law, obj, dll.empc_eval


def call(empc_eval, theta):
    du = ctypes.c_double(SENTINEL)
    code = empc_eval((ctypes.c_double * theta.size)(*theta), ctypes.byref(du))
    return code, du.value


def test_object_file_needs_no_library(compiled):
    """No malloc, no libm, no global state: the object references no external symbol."""
    _, obj, _ = compiled
    undefined = subprocess.run(["nm", "-u", str(obj)], capture_output=True, text=True,
                               check=True).stdout
    assert undefined.strip() == ""


def test_compiled_law_equals_python_law(compiled):
    law, _, empc_eval = compiled
    _, S = relative_map(law.qp, law.config.ht)
    rng = np.random.default_rng(7)
    lower, upper = law.box.lower, law.box.upper
    n_x = law.qp.n_x
    inside, _ = region_samples(law.solution, rng, 20)  # every region, thin ones included
    uniform = lower + (upper - lower) * rng.uniform(0.0, 1.0, (2500, lower.size))
    around = lower + (upper - lower) * rng.uniform(-0.2, 1.2, (1000, lower.size))
    codes = []
    for phi in np.vstack([inside, uniform, around]):
        theta = S @ phi
        y = rng.uniform(-5000.0, 5000.0)  # absolute positions after many revolutions
        theta[n_x - 1] += y
        theta[n_x + 1:] += y
        code, du = call(empc_eval, theta)
        expected_code, expected_du = law.first_move(theta)
        assert code == expected_code
        if code >= 0:
            assert du == pytest.approx(expected_du, rel=1e-12, abs=1e-9)
        else:
            assert du == SENTINEL  # untouched when no law applies
        codes.append(code)
    assert OUTSIDE_BOX in codes
    assert set(codes) - {OUTSIDE_BOX} == set(range(law.n_controllers))


def test_nan_parameter_is_outside_the_box(compiled):
    law, _, empc_eval = compiled
    theta = np.zeros(law.P.shape[1])
    assert call(empc_eval, theta)[0] == 0  # at rest: the unconstrained controller
    theta[0] = np.nan
    assert call(empc_eval, theta) == (OUTSIDE_BOX, SENTINEL)
    assert NOT_FOUND not in law.tree.label[law.tree.plane < 0]  # covered box: no gap leaf


def test_source_documents_its_interface(explicit_law):
    law = explicit_law(CASES["paper"])
    text = c_source(law)
    assert "int empc_eval(const double theta[], double *du)" in text
    assert "malloc" not in text and "#include" not in text
    for name in law.box.names:
        assert f" {name} " in text


def test_unwritable_path_is_one_clear_error(tmp_path, explicit_law):
    law = explicit_law(CASES["paper"])
    with pytest.raises(HilError, match="cannot write"):
        write_c(law, tmp_path / "missing" / "law.c")
