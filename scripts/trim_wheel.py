"""A Mitsuba wheel trimmed to what a device run needs, so that it travels to a device
machine beside the project (a call carries 64 MiB in all; Mitsuba 3.9.1's wheel is 62 MB).

Drops the variant modules not named by ``--keep-variants`` (1.3 MB each, compressed), the
C++ headers, and the plugins no scene of this package's benchmarks uses (volumes, curves,
polarization, ellipsoids, the particle tracer: :data:`DROPPED_PLUGINS`), and writes the wheel
again with its RECORD made anew (hashes and sizes of what is left), so that pip installs it
as it would the original.

    python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \\
        --platform manylinux_2_28_x86_64 -d .whl mitsuba==3.9.1 drjit==1.5.0
    python3 scripts/trim_wheel.py .whl/mitsuba-3.9.1-*.whl --keep-variants cuda_ad_rgb

The recipe that uses it: docs/USAGE.md, "On a GPU".
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import os
import re
import sys
import zipfile

DROPPED_PLUGINS = frozenset({
    "volpath", "volpathmis", "ptracer", "ellipsoids", "ellipsoidsmesh", "bsplinecurve", "linearcurve", "sdfgrid",
    "hair", "measured_polarized", "pplastic", "polarizer", "retarder", "gridvolume", "constvolume", "heterogeneous",
    "homogeneous", "sggx", "hg", "isotropic", "rayleigh", "tabphase", "blendphase", "stokes", "specfilm",
})
"""Plugins (file stems) that a rendering of surfaces under environments and lights never loads."""

VARIANT_MODULE = re.compile(r"^mitsuba/((?:scalar|llvm|cuda)_[a-z_]+)\.cpython-[^/]+\.so$")


def kept(name: str, variants: set[str]) -> bool:
    """Whether the wheel's member ``name`` stays."""
    variant = VARIANT_MODULE.match(name)
    if variant:
        return variant.group(1) in variants
    if name.startswith("mitsuba/include/"):
        return False
    if name.startswith("mitsuba/plugins/"):
        return os.path.splitext(os.path.basename(name))[0] not in DROPPED_PLUGINS
    return True


def record_line(name: str, data: bytes) -> str:
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return f"{name},sha256={digest},{len(data)}"


def trim(wheel: str, variants: set[str], out_dir: str) -> str:
    """Write the trimmed copy of ``wheel`` into ``out_dir`` (same file name); returns its path."""
    os.makedirs(out_dir, exist_ok=True)
    out = os.path.join(out_dir, os.path.basename(wheel))
    if os.path.abspath(out) == os.path.abspath(wheel):
        raise SystemExit("trim_wheel: --out must be another folder than the wheel's")
    with zipfile.ZipFile(wheel) as source, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as target:
        names = source.namelist()
        record = next(n for n in names if n.endswith(".dist-info/RECORD"))
        lines = []
        for name in names:
            if name == record or not kept(name, variants):
                continue
            data = source.read(name)
            target.writestr(source.getinfo(name), data, compress_type=zipfile.ZIP_DEFLATED, compresslevel=9)
            lines.append(record_line(name, data))
        target.writestr(record, "\n".join(lines + [f"{record},,"]) + "\n")
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("wheel")
    parser.add_argument("--keep-variants", nargs="+", default=["cuda_ad_rgb"])
    parser.add_argument("--out", default=None, help="folder of the trimmed wheel (default: the wheel's, "
                                                    "the original moved to ORIGINAL.whl.full)")
    args = parser.parse_args(argv)
    if args.out is None:
        full = args.wheel + ".full"
        os.replace(args.wheel, full)
        out = trim(full, set(args.keep_variants), os.path.dirname(os.path.abspath(args.wheel)) + "/.trim")
        os.replace(out, args.wheel)
        os.rmdir(os.path.dirname(out))
        out = args.wheel
    else:
        out = trim(args.wheel, set(args.keep_variants), args.out)
    print(f"{out}: {os.path.getsize(out) / 2**20:.1f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
