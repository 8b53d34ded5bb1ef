"""OpenCL runtime: discovery, selection, program build, build-error reporting."""
import numpy as np
import pyopencl as cl
import pytest

from dermis.pipeline import cl as dcl
from dermis.pipeline.errors import DermisError


def test01_default_device_is_pocl_cpu(cl_env):
    assert cl_env.is_pocl, cl_env.description
    assert cl_env.device.type & cl.device_type.CPU


def test02_list_devices_reports_capabilities():
    devs = dcl.list_devices()
    assert devs, "no OpenCL device listed"
    pocl = [d for d in devs if "Portable Computing Language" in d.platform]
    assert pocl and pocl[0].compute_units >= 1 and pocl[0].global_mem_mb > 0


def test03_select_by_index_and_name(cl_env):
    d = dcl.list_devices()[0]
    by_index = dcl.get_env(f"{d.platform_index}:{d.device_index}")
    by_name = dcl.get_env("portable computing")
    assert by_index.device.name.strip() == d.name
    assert by_name.is_pocl


def test04_unknown_device_is_a_clear_error():
    with pytest.raises(dcl.NoOpenCLError, match=r"no OpenCL device matches 'quantum'"):
        dcl.get_env("quantum")
    with pytest.raises(dcl.NoOpenCLError, match=r"'7:3' does not exist"):
        dcl.get_env("7:3")


def test05_env_var_selects_device(monkeypatch):
    monkeypatch.setenv(dcl.ENV_VAR, "no-such-device")
    with pytest.raises(dcl.NoOpenCLError, match="no-such-device"):
        dcl.get_env()


def test06_program_builds_with_shared_header_and_runs(cl_env, tmp_path, monkeypatch):
    src = tmp_path / "probe.cl"
    src.write_text('#include "common.h"\n__kernel void twice(__global float *x)'
                   '{ int i = get_global_id(0); x[i] = 2.0f * x[i] + sqr(0.0f) + DERMIS_PI * 0.0f; }\n')
    (tmp_path / "common.h").write_text((dcl.CL_DIR / "common.h").read_text())
    monkeypatch.setattr(dcl, "CL_DIR", tmp_path)
    x = np.arange(16, dtype=np.float32)
    buf = cl.Buffer(cl_env.context, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=x)
    ev = cl_env.kernel("probe.cl", "twice")(cl_env.queue, x.shape, None, buf)
    out = np.empty_like(x)
    cl.enqueue_copy(cl_env.queue, out, buf).wait()
    np.testing.assert_array_equal(out, 2 * x)
    assert dcl.event_seconds(ev) > 0.0


def test07_syntax_error_names_file_and_line(cl_env, tmp_path, monkeypatch):
    src = tmp_path / "broken.cl"
    src.write_text("__kernel void k(__global float *x)\n{\n    x[0] = 1.0f\n    x[1] = 2.0f;\n}\n")
    monkeypatch.setattr(dcl, "CL_DIR", tmp_path)
    with pytest.raises(dcl.KernelBuildError) as info:
        cl_env.program("broken.cl", defines={"MODE": 3})
    msg = str(info.value)
    assert msg.startswith(f"OpenCL build of {src}:3 failed") or msg.startswith(f"OpenCL build of {src}:4 failed"), msg
    assert "-DMODE=3" in msg and "compiler log" in msg
    assert isinstance(info.value, DermisError)


def test08_sources_hash_follows_includes(tmp_path, monkeypatch):
    (tmp_path / "a.cl").write_text('#include "h.h"\n')
    (tmp_path / "h.h").write_text("#define X 1\n")
    monkeypatch.setattr(dcl, "CL_DIR", tmp_path)
    h1 = dcl.kernel_sources_hash(["a.cl"])
    (tmp_path / "h.h").write_text("#define X 2\n")
    assert dcl.kernel_sources_hash(["a.cl"]) != h1


def test09_no_platform_gives_install_hint(monkeypatch):
    def boom():
        raise cl.LogicError("clGetPlatformIDs failed: PLATFORM_NOT_FOUND_KHR")
    monkeypatch.setattr(cl, "get_platforms", boom)
    with pytest.raises(dcl.NoOpenCLError, match="apt-get install pocl-opencl-icd"):
        dcl.list_devices()
