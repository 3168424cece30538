#!/usr/bin/env python3
"""A deterministic, ROS-like catkin workspace for the benchmarks.

``generate(root, files=7000, size_mb=150, seed=1)`` writes ``root/src`` with:

- packages laid out as catkin makes them: ``package.xml``, ``CMakeLists.txt``,
  ``src/*.cpp``, ``include/<pkg>/*.h``, ``scripts/*.py`` (executable),
  ``launch/*.launch``, ``config/*.yaml``, sometimes ``msg/*.msg`` and a README;
- ``*_description`` packages with meshes: binary STL (float32 triangles) and
  COLLADA ``.dae`` (XML with long float arrays), a few MB each;
- a few larger data files (an occupancy-grid map ``.pgm``, a recorded
  ``.bag``-like binary, a point cloud ``.pcd``);
- :data:`BIG_TEXT` (2 MiB of generated C++ tables) for the insert and rename cases;
- ``src/CMakeLists.txt``, the absolute symlink ``catkin_init_workspace`` makes.

Text is assembled from code-like line templates with per-package identifiers,
so it compresses about like real source (zlib level 6 to roughly a quarter);
binaries compress about like their real kinds. Everything derives from
``random.Random(seed)``, so the same arguments give byte-identical trees.
Generation is fast (~2 s for the default size): text is built from blocks, and
binary content from ``randbytes`` shaped with ``bytes.translate`` and slicing.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import random
import shutil
import time
from pathlib import Path

__all__ = ["BIG_TEXT", "CATKIN_TOPLEVEL", "Workspace", "generate"]

BIG_TEXT = "perception_tables/src/generated_lookup_tables.cpp"
"""Path under ``src/`` of the 2 MiB text file the insert and rename cases edit."""
BIG_TEXT_SIZE = 2 * 1024 * 1024

CATKIN_TOPLEVEL = "/opt/ros/noetic/share/catkin/cmake/toplevel.cmake"
"""Target of ``src/CMakeLists.txt``: absolute (dangling off a ROS machine), as catkin makes it."""

# Shares of the byte budget (after the big text file): source-like text, meshes, data files.
_TEXT_SHARE = 0.36
_MESH_SHARE = 0.40

_WORD_TEXT = (
    "pose odom base laser scan cloud point map goal path plan joint arm gripper head torso "
    "camera depth image imu wheel motor battery status state command velocity twist frame "
    "tf transform marker target grasp object detect track filter update config param node "
    "topic service action client server buffer queue timer rate error limit offset scale "
    "sensor driver controller planner costmap footprint obstacle trajectory segment cluster"
)
_WORDS = _WORD_TEXT.split()
_TYPES = (
    "double",
    "float",
    "int",
    "bool",
    "std::string",
    "size_t",
    "uint32_t",
    "ros::Time",
    "geometry_msgs::Pose",
    "sensor_msgs::LaserScan",
    "Eigen::Vector3d",
    "std::vector<double>",
)

# Line templates; {C} class, {f} function, {v}/{w} variables, {T} type, {P} package, {n} number.
_CPP_BLOCKS = (
    (
        "{T} {C}::{f}(const {T}& {v}, {T} {w})\n{{\n  if ({v} < {n})\n  {{\n"
        '    ROS_WARN_THROTTLE(1.0, "{P}: {v} below limit (%f)", static_cast<double>({v}));\n'
        "    return {w};\n  }}\n  {w} = {v} * {n}.{n};\n  return {w};\n}}\n\n"
    ),
    (
        "void {C}::{f}Callback(const {T}::ConstPtr& msg)\n{{\n"
        "  std::lock_guard<std::mutex> lock(mutex_);\n  last_{v}_ = *msg;\n"
        '  have_{v}_ = true;\n  ROS_DEBUG_NAMED("{P}", "received {v} %zu", {w}_count_++);\n}}\n\n'
    ),
    (
        'bool {C}::{f}()\n{{\n  ros::NodeHandle pnh("~");\n'
        '  pnh.param("{v}_{w}", {v}_{w}_, {n}.0);\n  pnh.param("use_{v}", use_{v}_, true);\n'
        '  {v}_sub_ = nh_.subscribe("{v}", {n}, &{C}::{v}Callback, this);\n'
        '  {w}_pub_ = nh_.advertise<{T}>("{w}", {n});\n  return true;\n}}\n\n'
    ),
    (
        "  for (size_t i = 0; i < {v}.size(); ++i)\n  {{\n"
        "    const auto& p = {v}[i];\n    if (!std::isfinite(p.{w}))\n      continue;\n"
        "    {w}_sum += p.{w} * {n}.{n};\n  }}\n"
    ),
    (
        "// {C}::{f} keeps the {v} and the {w} consistent; see the {P} design notes.\n"
        "// The {v} is expressed in the {w} frame unless use_{v}_ is false.\n"
    ),
    "{T} {C}::get{C}{n}() const\n{{\n  return {v}_{w}_;\n}}\n\n",
    (
        "  tf2::Transform {v}_to_{w};\n  tf2::fromMsg({v}.pose, {v}_to_{w});\n"
        "  const double yaw = tf2::getYaw({v}_to_{w}.getRotation());\n"
    ),
    (
        '  if (!tf_buffer_.canTransform("{v}", "{w}", ros::Time(0), ros::Duration({n}.0)))\n  {{\n'
        '    ROS_ERROR("{P}: no transform from {v} to {w}");\n    return false;\n  }}\n'
    ),
    (
        "  switch ({v}_state_)\n  {{\n    case State::IDLE:\n      {f}();\n      break;\n"
        "    case State::RUNNING:\n      {w}_count_ += {n};\n      break;\n"
        "    default:\n      break;\n  }}\n"
    ),
)
_H_BLOCKS = (
    "  /** Returns the {v} in the {w} frame; thread safe. */\n  {T} {f}(const {T}& {v}) const;\n",
    "  {T} {v}_{w}_;\n  bool have_{v}_ = false;\n",
    "  ros::Subscriber {v}_sub_;\n  ros::Publisher {w}_pub_;\n",
    "  void {v}Callback(const {T}::ConstPtr& msg);\n  bool {f}();\n",
    "  static constexpr double k{C}{n} = {n}.{n};\n",
)
_PY_BLOCKS = (
    (
        '    def {f}(self, {v}, {w}={n}):\n        """Return the {v} scaled to the {w} frame."""\n'
        '        if {v} is None:\n            rospy.logwarn("{P}: no {v} yet")\n'
        "            return {w}\n"
        "        return {v} * {n}.{n} + {w}\n\n"
    ),
    (
        "    def {v}_cb(self, msg):\n        with self._lock:\n            self._{v} = msg\n"
        "            self._{w}_count += 1\n\n"
    ),
    (
        '        self.{v}_pub = rospy.Publisher("{v}", {C}, queue_size={n})\n'
        '        self.{w}_sub = rospy.Subscriber("{w}", {C}, self.{w}_cb)\n'
    ),
    '        {v} = rospy.get_param("~{v}_{w}", {n}.0)\n        rate = rospy.Rate({n})\n',
)
_YAML_BLOCK = (
    "{v}_{w}:\n  enabled: true\n  rate: {n}.0\n  frame_id: {v}_link\n  topic: /{P}/{w}\n"
    "  gain: [{n}.0, 0.{n}, {n}.{n}]\n"
)
_LAUNCH_BLOCK = (
    '  <node pkg="{P}" type="{v}_{w}_node" name="{v}_{w}" output="screen">\n'
    '    <param name="{v}_rate" value="{n}.0"/>\n    <remap from="{v}" to="/{P}/{w}"/>\n'
    '    <rosparam file="$(find {P})/config/{v}.yaml" command="load"/>\n  </node>\n'
)
_LICENSE = (
    "/*\n * Copyright (c) {n}, Example Robotics, Inc.\n * All rights reserved.\n *\n"
    " * Redistribution and use in source and binary forms, with or without\n"
    " * modification, are permitted provided that the conditions in LICENSE are met.\n */\n\n"
)


@dataclasses.dataclass(frozen=True)
class Workspace:
    root: Path
    src: Path
    files: int
    bytes: int
    symlinks: int
    big_text: Path
    edit_target: Path
    """A mid-sized .cpp whose line the one-edit case changes."""
    seconds: float


class _Gen:
    def __init__(self, seed: int) -> None:
        self.rng = random.Random(seed)

    def name(self, parts: int = 2) -> str:
        return "_".join(self.rng.choice(_WORDS) for _ in range(parts))

    def camel(self) -> str:
        return "".join(w.capitalize() for w in self.name(2).split("_"))

    def fill(self, template: str, pkg: str) -> str:
        r = self.rng
        return template.format(
            C=self.camel(),
            f=r.choice(_WORDS) + r.choice(_WORDS).capitalize(),
            v=r.choice(_WORDS),
            w=r.choice(_WORDS),
            T=r.choice(_TYPES),
            P=pkg,
            n=r.randrange(1, 500),
        )

    def text(
        self, blocks: tuple[str, ...], pkg: str, size: int, head: str = "", tail: str = ""
    ) -> bytes:
        parts = [head]
        n = len(head) + len(tail)
        while n < size:
            s = self.fill(self.rng.choice(blocks), pkg)
            parts.append(s)
            n += len(s)
        parts.append(tail)
        return "".join(parts).encode()

    def text_size(self, mean: int) -> int:
        # Source file sizes are roughly log-normal: many small files, a long tail.
        return max(200, min(int(self.rng.lognormvariate(0, 0.8) * mean * 0.73), mean * 12))

    # -- binaries ------------------------------------------------------------------------
    def floats(self, n: int) -> bytes:
        """``n`` little-endian float32 values of about -8..8 in mm steps: mesh coordinates."""
        r = self.rng
        buf = bytearray(4 * n)
        buf[0::4] = r.randbytes(n)
        buf[1::4] = r.randbytes(n)
        # Mantissa top bits from fewer values, exponents from a handful: shaped like
        # coordinates of one part, which is what makes real meshes compress a little.
        buf[2::4] = r.randbytes(n).translate(
            bytes((b & 0x7F) | 0x80 if b & 0x80 else b & 0x3F for b in range(256))
        )
        buf[3::4] = r.randbytes(n).translate(
            bytes((0x3E, 0x3F, 0x40, 0x40, 0xBE, 0xBF, 0xC0, 0xC0)[b & 7] for b in range(256))
        )
        return bytes(buf)

    def stl(self, size: int, solid: str) -> bytes:
        tris = max(1, (size - 84) // 50)
        header = f"binary STL {solid}".encode().ljust(80, b"\0")
        coords = self.floats(tris * 12)
        body = bytearray(tris * 50)
        for k in range(12 * 4):  # 48 coordinate bytes of each 50-byte record
            body[k::50] = coords[k::48]
        return header + tris.to_bytes(4, "little") + bytes(body)

    def dae(self, size: int, name: str) -> bytes:
        head = (
            '<?xml version="1.0" encoding="utf-8"?>\n'
            '<COLLADA xmlns="http://www.collada.org/2005/11/COLLADASchema" version="1.4.1">\n'
            f'  <library_geometries>\n    <geometry id="{name}-mesh" name="{name}">\n'
            f'      <mesh>\n        <source id="{name}-mesh-positions">\n'
            f'          <float_array id="{name}-mesh-positions-array">'
        )
        tail = (
            "</float_array>\n        </source>\n      </mesh>\n    </geometry>\n"
            "  </library_geometries>\n</COLLADA>\n"
        )
        n = max(0, size - len(head) - len(tail))
        # digits with separators and signs, about the entropy of printed floats
        table = bytes(b"0123456789012345678901234567890123456789 .-"[b % 43] for b in range(256))
        return head.encode() + self.rng.randbytes(n).translate(table) + tail.encode()

    def pgm(self, size: int) -> bytes:
        w = 2048
        h = max(1, (size - 20) // w)
        head = f"P5\n{w} {h}\n255\n".encode()
        r = self.rng
        rows = []
        # free space, walls and unknown in runs, as a map_server map looks
        for _ in range(h):
            row = bytearray(b"\xcd" * w)
            a = r.randrange(0, w // 3)
            b = r.randrange(w // 2, w)
            row[a:b] = b"\xfe" * (b - a)
            for _ in range(r.randrange(2, 12)):
                x = r.randrange(a, b)
                row[x : x + r.randrange(1, 6)] = b"\x00" * len(row[x : x + 5])
            rows.append(bytes(row[:w]))
        return head + b"".join(rows)

    def blob(self, size: int) -> bytes:
        """Mostly incompressible recorded data (a bag of compressed images and scans)."""
        data = bytearray(self.rng.randbytes(size))
        # message headers every few KB, like a bag's connection records
        for off in range(0, size - 64, 4096):
            data[off : off + 32] = b"op=\x02conn=\x00\x00\x00\x00time=\x00\x00\x00\x00topic=/sc"
        return bytes(data)


def _write(path: Path, data: bytes, mode: int = 0o644) -> None:
    with open(path, "wb") as fh:
        fh.write(data)
    if mode != 0o644:
        os.chmod(path, mode)


def _package_xml(pkg: str, deps: list[str]) -> bytes:
    lines = [
        '<?xml version="1.0"?>',
        '<package format="2">',
        f"  <name>{pkg}</name>",
        "  <version>0.3.1</version>",
        f"  <description>The {pkg.replace('_', ' ')} package.</description>",
        '  <maintainer email="dev@example.com">Robot Developer</maintainer>',
        "  <license>BSD</license>",
        "  <buildtool_depend>catkin</buildtool_depend>",
    ]
    lines += [f"  <depend>{d}</depend>" for d in deps]
    lines += ["</package>", ""]
    return "\n".join(lines).encode()


def _cmakelists(pkg: str, deps: list[str], cpp: list[str]) -> bytes:
    d = " ".join(deps)
    srcs = "\n  ".join(f"src/{c}" for c in cpp)
    return (
        "cmake_minimum_required(VERSION 3.0.2)\n"
        f"project({pkg})\n\n"
        "add_compile_options(-std=c++14)\n\n"
        f"find_package(catkin REQUIRED COMPONENTS\n  {d}\n)\n\n"
        "catkin_package(\n  INCLUDE_DIRS include\n"
        f"  LIBRARIES {pkg}\n  CATKIN_DEPENDS {d}\n)\n\n"
        "include_directories(include ${catkin_INCLUDE_DIRS})\n\n"
        f"add_library({pkg}\n  {srcs}\n)\n"
        f"target_link_libraries({pkg} ${{catkin_LIBRARIES}})\n\n"
        f"add_executable({pkg}_node src/{cpp[0]})\n"
        f"target_link_libraries({pkg}_node {pkg} ${{catkin_LIBRARIES}})\n\n"
        f"install(TARGETS {pkg} {pkg}_node\n"
        "  RUNTIME DESTINATION ${CATKIN_PACKAGE_BIN_DESTINATION}\n"
        "  LIBRARY DESTINATION ${CATKIN_PACKAGE_LIB_DESTINATION}\n)\n"
    ).encode()


def generate(root: Path, *, files: int = 7000, size_mb: float = 150, seed: int = 1) -> Workspace:
    """Write ``root/src`` (removing an old one) and describe it."""
    t0 = time.perf_counter()
    root = Path(root).resolve()
    src = root / "src"
    if src.exists() or src.is_symlink():
        shutil.rmtree(src)
    src.mkdir(parents=True)
    g = _Gen(seed)
    rng = g.rng
    budget = int(size_mb * 1024 * 1024) - BIG_TEXT_SIZE
    text_budget = int(budget * _TEXT_SHARE)
    mesh_budget = int(budget * _MESH_SHARE)
    n_meshes = max(2, min(files // 250, int(mesh_budget / (2.5 * 1024 * 1024)) or 2))
    n_data = 3
    # the top-level symlink, the big text file and its package's two files, meshes, data
    text_files = max(20, files - 1 - 3 - n_meshes - n_data)
    mean_text = max(300, text_budget // text_files)

    count = 0
    total = 0
    edit_target: Path | None = None

    def put(rel: str, data: bytes, mode: int = 0o644) -> Path:
        nonlocal count, total
        p = src / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        _write(p, data, mode)
        count += 1
        total += len(data)
        return p

    os.symlink(CATKIN_TOPLEVEL, src / "CMakeLists.txt")

    # The big text file lives in its own package.
    big_head = (
        _LICENSE.format(n=2019)
        + "#include <array>\n#include <cstdint>\n\nnamespace perception_tables\n{\n"
    )
    big = g.text(
        _CPP_BLOCKS, "perception_tables", BIG_TEXT_SIZE - 32, big_head, "}  // namespace\n"
    )
    big = (
        big[: BIG_TEXT_SIZE - 1] + b"\n"
        if len(big) >= BIG_TEXT_SIZE
        else big.ljust(BIG_TEXT_SIZE - 1, b" ") + b"\n"
    )
    big_path = put(BIG_TEXT, big)
    put("perception_tables/package.xml", _package_xml("perception_tables", ["roscpp"]))
    put(
        "perception_tables/CMakeLists.txt",
        _cmakelists("perception_tables", ["roscpp"], ["generated_lookup_tables.cpp"]),
    )

    used: set[str] = set()
    pkgs_made = 0
    while count < 4 + text_files:
        pkg = g.name(2)
        if pkg in used:
            pkg = f"{pkg}_{pkgs_made}"
        used.add(pkg)
        pkgs_made += 1
        deps = rng.sample(
            [
                "roscpp",
                "rospy",
                "std_msgs",
                "sensor_msgs",
                "geometry_msgs",
                "tf2_ros",
                "nav_msgs",
                "actionlib",
                "dynamic_reconfigure",
                "message_generation",
            ],
            rng.randrange(2, 6),
        )
        n_cpp = rng.randrange(4, 15)
        cpp = [f"{g.name(2)}_{i}.cpp" for i in range(n_cpp)]
        pending: list[tuple[str, bytes, int]] = [
            (f"{pkg}/package.xml", _package_xml(pkg, deps), 0o644),
            (f"{pkg}/CMakeLists.txt", _cmakelists(pkg, deps, cpp), 0o644),
        ]
        lic = _LICENSE.format(n=2010 + rng.randrange(14))
        for c in cpp:
            head = (
                lic
                + f"#include <{pkg}/{c[:-4]}.h>\n#include <ros/ros.h>\n#include <mutex>\n\n"
                + f"namespace {pkg}\n{{\n\n"
            )
            pending.append(
                (
                    f"{pkg}/src/{c}",
                    g.text(
                        _CPP_BLOCKS, pkg, g.text_size(mean_text), head, f"}}  // namespace {pkg}\n"
                    ),
                    0o644,
                )
            )
        for i in range(rng.randrange(3, 11)):
            hname = cpp[i][:-4] if i < len(cpp) else f"{g.name(2)}_{i}"
            guard = f"{pkg}_{hname}_H".upper()
            head = (
                lic
                + f"#ifndef {guard}\n#define {guard}\n\n#include <ros/ros.h>\n\n"
                + f"namespace {pkg}\n{{\nclass {g.camel()}\n{{\npublic:\n"
            )
            pending.append(
                (
                    f"{pkg}/include/{pkg}/{hname}.h",
                    g.text(
                        _H_BLOCKS,
                        pkg,
                        g.text_size(mean_text) // 2,
                        head,
                        f"}};\n}}  // namespace {pkg}\n#endif  // {guard}\n",
                    ),
                    0o644,
                )
            )
        for i in range(rng.randrange(0, 6)):
            head = (
                f'#!/usr/bin/env python3\n"""{pkg}: {g.name(3).replace("_", " ")}."""\n\n'
                "import threading\n\nimport rospy\n\n\nclass " + g.camel() + "(object):\n"
                "    def __init__(self):\n        self._lock = threading.Lock()\n\n"
            )
            pending.append(
                (
                    f"{pkg}/scripts/{g.name(2)}_{i}.py",
                    g.text(
                        _PY_BLOCKS,
                        pkg,
                        g.text_size(mean_text),
                        head,
                        "\n\nif __name__ == '__main__':\n"
                        "    rospy.init_node('n')\n    rospy.spin()\n",
                    ),
                    0o755,
                )
            )
        for i in range(rng.randrange(1, 5)):
            pending.append(
                (
                    f"{pkg}/launch/{g.name(2)}_{i}.launch",
                    g.text(
                        (_LAUNCH_BLOCK,),
                        pkg,
                        g.text_size(mean_text) // 3,
                        "<launch>\n",
                        "</launch>\n",
                    ),
                    0o644,
                )
            )
        for i in range(rng.randrange(1, 5)):
            pending.append(
                (
                    f"{pkg}/config/{g.name(2)}_{i}.yaml",
                    g.text(
                        (_YAML_BLOCK,), pkg, g.text_size(mean_text) // 3, f"# {pkg} parameters\n"
                    ),
                    0o644,
                )
            )
        if rng.random() < 0.3:
            for i in range(rng.randrange(1, 5)):
                fields = "".join(
                    f"{rng.choice(_TYPES[:3]).replace('double', 'float64')} {g.name(2)}\n"
                    for _ in range(rng.randrange(2, 10))
                )
                pending.append(
                    (f"{pkg}/msg/{g.camel()}{i}.msg", ("Header header\n" + fields).encode(), 0o644)
                )
        if rng.random() < 0.5:
            pending.append(
                (f"{pkg}/README.md", g.text(_CPP_BLOCKS[4:5], pkg, 1500, f"# {pkg}\n\n"), 0o644)
            )
        for rel, data, mode in pending:
            if count >= 4 + text_files:
                break
            p = put(rel, data, mode)
            if edit_target is None and rel.endswith(".cpp") and 4000 < len(data) < 20000:
                edit_target = p

    # description packages with meshes
    mesh_each = mesh_budget // n_meshes
    for i in range(n_meshes):
        desc = f"robot_part{i // 6}_description"
        size = int(mesh_each * (0.6 + 0.8 * rng.random()))
        if i % 3 == 2:
            put(f"{desc}/meshes/{g.name(2)}_{i}.dae", g.dae(size, f"link{i}"))
        else:
            put(f"{desc}/meshes/{g.name(2)}_{i}.stl", g.stl(size, f"link{i}"))
    # a few larger data files take what the budget has left (text runs short or long)
    data_budget = max(3 * 64 * 1024, int(size_mb * 1024 * 1024) - total)
    put("navigation_maps/maps/building_floor2.pgm", g.pgm(int(data_budget * 0.3)))
    put("perception_tables/data/calibration_run.bag", g.blob(int(data_budget * 0.45)))
    put(
        "perception_tables/data/lab_scan.pcd",
        g.stl(data_budget - int(data_budget * 0.3) - int(data_budget * 0.45), "pcd"),
    )

    assert edit_target is not None, "no .cpp of a suitable size to edit"
    return Workspace(
        root=root,
        src=src,
        files=count,
        bytes=total,
        symlinks=1,
        big_text=big_path,
        edit_target=edit_target,
        seconds=time.perf_counter() - t0,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("root", type=Path)
    ap.add_argument("--files", type=int, default=7000)
    ap.add_argument("--size-mb", type=float, default=150)
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
    ws = generate(a.root, files=a.files, size_mb=a.size_mb, seed=a.seed)
    print(
        f"{ws.src}: {ws.files} files, {ws.bytes / 2**20:.1f} MiB, {ws.symlinks} symlink, "
        f"in {ws.seconds:.2f} s"
    )


if __name__ == "__main__":
    main()
