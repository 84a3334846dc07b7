"""``crtk_msgs/OperatingState`` for rclpy, built from its message definition with the rosidl wheels.

The CRTK messages (https://github.com/collaborative-robotics/crtk_msgs) are not among the ROS 2
wheels on pip, and the dVRK publishes an arm's operating state as ``crtk_msgs/OperatingState``
(``<ns>/operating_state``). A ROS installation would build the package with colcon; here the
rosidl generators of the ``ros-jazzy-rosidl-*`` wheels generate its C, Fast DDS type support and
Python sources (the same generators colcon runs, called without CMake or ament) and the machine's
C and C++ compilers build them into a small package ``crtk_msgs`` (its own shared libraries and
a Python extension) in a cache folder: ``~/.cache/pointfence/crtk_msgs/<key>`` (or
``$POINTFENCE_CACHE``), keyed by the definition and the Python version. The build runs once (a
few seconds); ``operating_state_type()`` then imports the message class.

Only ``OperatingState`` is built (the one message the CRTK arm reads): its definition is
``std_msgs/Header header``, ``string state`` (``DISABLED``, ``ENABLED``, ``PAUSED``, ``FAULT``),
``bool is_homed``, ``bool is_busy``; its DDS type (``crtk_msgs::msg::dds_::OperatingState_``)
and wire form are those of the real package, so it interoperates with a dVRK's.

``python -m pointfence.service.ros2.crtk_msgs_build`` builds it and prints where.
"""
from __future__ import annotations

import ctypes
import hashlib
import importlib
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import threading
from pathlib import Path
from typing import Optional

from pointfence.kernels.errors import BackendUnavailable

PACKAGE = "crtk_msgs"
#: the message definition, as IDL (what rosidl's msg -> idl adapter writes; the adapter itself
#: needs catkin_pkg, which the wheels do not bring)
OPERATING_STATE_IDL = """\
// crtk_msgs/msg/OperatingState.msg (https://github.com/collaborative-robotics/crtk_msgs), as IDL
#include "std_msgs/msg/Header.idl"

module crtk_msgs {
  module msg {
    struct OperatingState {
      std_msgs::msg::Header header;

      string state;

      boolean is_homed;

      boolean is_busy;
    };
  };
};
"""
PACKAGE_XML = """<?xml version="1.0"?>
<package format="3"><name>crtk_msgs</name><version>1.1.0</version>
<description>CRTK messages (OperatingState only), built by pointfence</description>
<maintainer email="none@example.com">pointfence</maintainer><license>BSD-3-Clause</license>
<depend>std_msgs</depend><member_of_group>rosidl_interface_packages</member_of_group></package>
"""

_lock = threading.Lock()
_type = None


def _ros_prefix() -> Path:
    """The prefix the ROS 2 wheels are installed under (lib/, include/, share/)."""
    try:
        import rosidl_generator_c
    except ImportError as e:
        raise BackendUnavailable(f"the rosidl generators are not installed ({e}): pip install 'pointfence[ros2]'") from None
    return Path(rosidl_generator_c.__file__).resolve().parents[4]


def cache_dir() -> Path:
    """Where the built package lives: one folder per definition and Python version."""
    base = Path(os.environ.get("POINTFENCE_CACHE") or Path.home() / ".cache" / "pointfence")
    key = hashlib.sha256((OPERATING_STATE_IDL + sys.version + str(_ros_prefix())).encode()).hexdigest()[:12]
    return base / "crtk_msgs" / key


def _run(cmd: list, cwd: Path) -> None:
    r = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    if r.returncode != 0:
        raise BackendUnavailable(f"building crtk_msgs failed: {' '.join(cmd[:3])} ... exited {r.returncode}:\n"
                                 f"{(r.stderr or r.stdout)[-2000:]}")


def _generate(src: Path, out: Path, prefix: Path) -> None:
    """The rosidl generators (C, C type support, Fast DDS and introspection C type supports, Python) into
    ``out/<kind>/crtk_msgs``, called as colcon's CMake would, in a child interpreter (they look up
    their templates through the ament index)."""
    code = (
        "import pathlib, sys\n"
        "from rosidl_generator_c.cli import GenerateC\n"
        "from rosidl_typesupport_c.cli import GenerateCTypesupport\n"
        "from rosidl_typesupport_fastrtps_c.cli import GenerateFastRTPSCTypesupport\n"
        "from rosidl_typesupport_introspection_c.cli import GenerateIntrospectionCTypesupport\n"
        "from rosidl_generator_py.cli import GeneratePython\n"
        "src, out, share = sys.argv[1:4]\n"
        "files = [src + ':msg/OperatingState.idl']\n"
        "for kind, cls in (('c', GenerateC), ('ts_c', GenerateCTypesupport),\n"
        "                  ('fastrtps_c', GenerateFastRTPSCTypesupport),\n"
        "                  ('introspection_c', GenerateIntrospectionCTypesupport), ('py', GeneratePython)):\n"
        "    cls(kind).generate('crtk_msgs', files, [share], pathlib.Path(out) / kind / 'crtk_msgs')\n")
    env = {**os.environ, "AMENT_PREFIX_PATH": str(prefix)}
    r = subprocess.run([sys.executable, "-c", code, str(src), str(out), str(prefix / "share")],
                       capture_output=True, text=True, env=env)
    if r.returncode != 0:
        raise BackendUnavailable(f"generating crtk_msgs with rosidl failed:\n{r.stderr[-2000:]}")


def build(dest: Optional[Path] = None) -> Path:
    """Generate and compile the package into ``dest`` (default ``cache_dir()``); returns ``dest``,
    which holds ``crtk_msgs/`` (the Python package) and ``lib/`` (its shared libraries). Raises
    ``BackendUnavailable`` saying what failed (no compiler, a generator error)."""
    prefix = _ros_prefix()
    dest = Path(dest) if dest is not None else cache_dir()
    cc, cxx = os.environ.get("CC", "cc"), os.environ.get("CXX", "c++")
    for tool in (cc, cxx):
        if shutil.which(tool) is None:
            raise BackendUnavailable(f"building crtk_msgs needs a C and a C++ compiler; {tool!r} was not found "
                                     "(set CC / CXX)")
    dest.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="crtk_msgs-", dir=dest.parent))
    try:
        src = work / "src"
        (src / "msg").mkdir(parents=True)
        (src / "msg" / "OperatingState.idl").write_text(OPERATING_STATE_IDL)
        (src / "package.xml").write_text(PACKAGE_XML)
        gen = work / "gen"
        _generate(src, gen, prefix)
        lib, pkg = work / "out" / "lib", work / "out" / PACKAGE
        lib.mkdir(parents=True)
        (pkg / "msg").mkdir(parents=True)
        inc = [f"-I{gen / k}" for k in ("c", "fastrtps_c", "introspection_c")] + [f"-I{prefix / 'include'}"] + [f"-I{d}" for d in sorted((prefix / "include").iterdir())
                                                               if d.is_dir()]
        # run paths relative to each file ($ORIGIN), so the finished tree can move into place
        rpath = ["-Wl,-rpath,$ORIGIN", "-Wl,-rpath,$ORIGIN/../lib", f"-Wl,-rpath,{prefix / 'lib'}", f"-L{lib}",
                 f"-L{prefix / 'lib'}"]
        c, fast, ts, intro, py = (gen / k / PACKAGE / "msg" for k in ("c", "fastrtps_c", "ts_c", "introspection_c", "py"))
        flags = ["-shared", "-fPIC", "-O2", "-w"]
        name = f"lib{PACKAGE}__%s.so"
        _run([cc, *flags, *inc, *sorted(str(p) for p in (c / "detail").glob("*.c")), "-o", str(lib / (name % "rosidl_generator_c")), f"-Wl,-soname,{name % 'rosidl_generator_c'}",
              *rpath, "-lrosidl_runtime_c", "-lrcutils", "-lstd_msgs__rosidl_generator_c",
              "-lbuiltin_interfaces__rosidl_generator_c"], work)
        _run([cxx, *flags, "-std=c++17", *inc, str(fast / "detail" / "operating_state__type_support_c.cpp"),
              "-o", str(lib / (name % "rosidl_typesupport_fastrtps_c")), f"-Wl,-soname,{name % 'rosidl_typesupport_fastrtps_c'}", *rpath, f"-l{PACKAGE}__rosidl_generator_c",
              "-lrosidl_typesupport_fastrtps_c", "-lrosidl_typesupport_fastrtps_cpp", "-lfastcdr", "-lrmw",
              "-lrosidl_runtime_c", "-lstd_msgs__rosidl_typesupport_fastrtps_c",
              "-lbuiltin_interfaces__rosidl_typesupport_fastrtps_c", "-lrcutils"], work)
        # (Fast DDS builds the type object from the introspection type support)
        _run([cc, *flags, *inc, str(intro / "detail" / "operating_state__type_support.c"),
              "-o", str(lib / (name % "rosidl_typesupport_introspection_c")),
              f"-Wl,-soname,{name % 'rosidl_typesupport_introspection_c'}", *rpath, f"-l{PACKAGE}__rosidl_generator_c",
              "-lrosidl_typesupport_introspection_c", "-lstd_msgs__rosidl_typesupport_introspection_c",
              "-lstd_msgs__rosidl_generator_c", "-lrosidl_runtime_c", "-lrcutils"], work)
        _run([cxx, *flags, "-std=c++17", *inc, str(ts / "operating_state__type_support.cpp"),
              "-o", str(lib / (name % "rosidl_typesupport_c")), f"-Wl,-soname,{name % 'rosidl_typesupport_c'}", *rpath, f"-l{PACKAGE}__rosidl_generator_c",
              "-lrosidl_typesupport_c", "-lrosidl_runtime_c", "-lrcutils"], work)
        ext = sysconfig.get_config_var("EXT_SUFFIX") or ".so"
        numpy_inc = []
        try:
            import numpy
            numpy_inc = [f"-I{numpy.get_include()}"]
        except ImportError:
            pass
        _run([cc, *flags, *inc, f"-I{sysconfig.get_paths()['include']}", *numpy_inc,
              str(py.parent / f"_{PACKAGE}_s.ep.rosidl_typesupport_c.c"), str(py / "_operating_state_s.c"),
              "-o", str(pkg / f"{PACKAGE}_s__rosidl_typesupport_c{ext}"), *rpath,
              f"-l{PACKAGE}__rosidl_typesupport_c", f"-l{PACKAGE}__rosidl_generator_c",
              "-lstd_msgs__rosidl_generator_py", "-lstd_msgs__rosidl_generator_c",
              "-lbuiltin_interfaces__rosidl_generator_py", "-lrosidl_runtime_c", "-lrcutils"], work)
        for f in py.glob("*.py"):
            shutil.copy(f, pkg / "msg" / f.name)
        (pkg / "__init__.py").write_text('"""crtk_msgs (OperatingState), built by pointfence.service.ros2.crtk_msgs_build."""\n')
        # one atomic rename: a process building beside this one (the robot process, a sim-arm)
        # either finds the whole package or none; the first build in place wins
        if dest.exists() and not (dest / PACKAGE / "msg" / "_operating_state.py").exists():
            shutil.rmtree(dest)            # (a damaged folder)
        try:
            os.rename(work / "out", dest)
        except OSError:
            if not (dest / PACKAGE / "msg" / "_operating_state.py").exists():
                raise
        return dest
    finally:
        shutil.rmtree(work, ignore_errors=True)


def operating_state_type():
    """The ``crtk_msgs.msg.OperatingState`` class, built on first use (``build``). Raises
    ``BackendUnavailable`` when it cannot be built here (what failed, and how to get it)."""
    global _type
    with _lock:
        if _type is not None:
            return _type
        try:   # a real crtk_msgs (a ROS installation, a colcon workspace) wins
            from crtk_msgs.msg import OperatingState
            _type = OperatingState
            return _type
        except ImportError:
            pass
        d = cache_dir()
        if not (d / PACKAGE / "msg" / "_operating_state.py").exists():
            try:
                build(d)
            except BackendUnavailable as e:
                raise BackendUnavailable(f"{e}\n(without crtk_msgs: [robot] operating_state_type = \"string\" reads the "
                                         "state from a std_msgs/String, \"none\" goes by measured_cp alone; see "
                                         "service/robot/README.md)") from None
        # rosidl_typesupport_c dlopens the Fast DDS type support library by its bare name: loaded
        # here first (by path, global), it is found by its soname
        for kind in ("rosidl_generator_c", "rosidl_typesupport_fastrtps_c", "rosidl_typesupport_introspection_c",
                     "rosidl_typesupport_c"):
            ctypes.CDLL(str(d / "lib" / f"lib{PACKAGE}__{kind}.so"), mode=ctypes.RTLD_GLOBAL)
        if str(d) not in sys.path:
            sys.path.insert(0, str(d))
        importlib.invalidate_caches()
        mod = importlib.import_module(f"{PACKAGE}.msg")
        _type = mod.OperatingState
        return _type


if __name__ == "__main__":
    print(build())
