"""NeXus building blocks shared by result files, run files and table downloads."""

from __future__ import annotations

import json
from collections.abc import Mapping

import h5py
import numpy as np

from analysis.formats.particle_table import UNITS


def nx_group(parent: h5py.Group, name: str, nx_class: str) -> h5py.Group:
    group = parent.create_group(name)
    group.attrs["NX_class"] = nx_class
    return group


def write_table(group: h5py.Group, columns: Mapping[str, np.ndarray]) -> None:
    names = list(columns)
    group.attrs["signal"] = "Z" if "Z" in columns else (names[0] if names else "")
    group.attrs["columns"] = json.dumps(names)
    for name in names:
        data = np.asarray(columns[name])
        if data.dtype.kind == "U":
            data = data.astype(object)
            ds = group.create_dataset(name, data=data, dtype=h5py.string_dtype())
        else:
            ds = group.create_dataset(name, data=data)
        if name in UNITS:
            ds.attrs["units"] = UNITS[name]


def read_table(group: h5py.Group) -> dict[str, np.ndarray]:
    names = json.loads(group.attrs["columns"])
    out = {}
    for name in names:
        data = group[name][()]
        if data.dtype.kind == "O":
            data = np.array([v.decode() if isinstance(v, bytes) else v for v in data], dtype=str)
        out[name] = data
    return out


def write_process(entry: h5py.Group, parameters: dict) -> None:
    process = nx_group(entry, "process", "NXprocess")
    process["program"] = "plenodust"
    from importlib.metadata import PackageNotFoundError, version
    try:
        process["version"] = version("plenodust")
    except PackageNotFoundError:
        process["version"] = "unknown"
    process["parameters"] = json.dumps(parameters, sort_keys=True, default=str)
