"""The simulated CANopen devices' non-volatile memory for plain dictionary values (PDO set-up, heartbeat time,
drive settings), by node and CiA 301 parameter category, optionally kept in a JSON file next to the state file.

The parameter set the devices store through the controller model (geometry, compensation, home offsets) lives in
the simulator's state file (``sim_devices.sim_state``); this memory holds the rest of what 1010h stores. The file is
replaced atomically (temp file + ``os.replace``, fsynced), so a killed simulator leaves the old or the new content.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from enum import Enum
from pathlib import Path


class Category(Enum):
    """Parameter categories of 1010h/1011h (CiA 301 7.5.2.13): index ranges."""

    COMMUNICATION = (0x1000, 0x1FFF)
    APPLICATION = (0x6000, 0x9FFF)
    MANUFACTURER = (0x2000, 0x5FFF)

    def contains(self, index: int) -> bool:
        return self.value[0] <= index <= self.value[1]

    @staticmethod
    def of_sub_index(sub: int) -> tuple[Category, ...]:
        """Sub-index 1: all; 2: communication; 3: application; 4: manufacturer-specific (this device's choice)."""
        return {1: tuple(Category), 2: (Category.COMMUNICATION,), 3: (Category.APPLICATION,),
                4: (Category.MANUFACTURER,)}[sub]


def _key(index: int, sub: int) -> str:
    return f"{index:04X}:{sub:02X}"


class Nvram:
    """Stored dictionary values per node; ``path`` None keeps them for the life of the process only."""

    def __init__(self, path: Path | None = None) -> None:
        self.path = path
        self._data: dict[str, dict[str, str]] = {}
        if path is not None and path.exists():
            loaded = json.loads(path.read_text())
            if not isinstance(loaded, dict):
                raise ValueError(f"{path}: not a CANopen non-volatile memory file")
            self._data = {str(node): dict(values) for node, values in loaded.items()}

    def entries(self, node_id: int) -> dict[tuple[int, int], bytes]:
        """Every stored value of a node."""
        out = {}
        for key, text in self._data.get(str(node_id), {}).items():
            index, sub = key.split(":")
            out[(int(index, 16), int(sub, 16))] = bytes.fromhex(text)
        return out

    def put(self, node_id: int, categories: tuple[Category, ...], values: Mapping[tuple[int, int], bytes]) -> None:
        """Replace a node's stored values of these categories (empty: back to the defaults) and write the file."""
        node = {k: v for k, v in self._data.get(str(node_id), {}).items()
                if not any(c.contains(int(k.split(":")[0], 16)) for c in categories)}
        node.update({_key(index, sub): data.hex() for (index, sub), data in values.items()})
        self._data[str(node_id)] = node
        self._write()

    def _write(self) -> None:
        if self.path is None:
            return
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        with open(tmp, "w") as fh:
            json.dump(self._data, fh, indent=1, sort_keys=True)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, self.path)
