"""hilcal.protocols.ippdme's error table, read against the specification's own text (8.2 of I++ DME 1.4.3): every
predefined error with its default severity and exact text, nothing more."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from hilcal.protocols.ippdme import ERRORS

SPEC = Path("/work/shared/reference/ippdme/Iplusplus_DME_Spec_1.4.3.txt")


@pytest.mark.skipif(not SPEC.is_file(), reason="the specification's text is not available here")
def test_the_error_table_is_8_2s() -> None:
    text = SPEC.read_text(encoding="latin-1")
    block = text[text.index("Defined errors:") :][:4000]
    table = {int(m.group(2)): (int(m.group(1)), m.group(3).strip())
             for m in re.finditer(r"^([0-9]) +([0-9]{4}) (.+?)\s*$", block, re.M)}
    assert len(table) == 52
    assert {code: (int(e.severity), e.text) for code, e in ERRORS.items()} == table
