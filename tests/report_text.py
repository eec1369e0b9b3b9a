"""What a report's text must not hold (issue 85): a difference stated without its standard error. A difference is
written with its sign (+0.123; negative ones in the same format, so the positive ones stand for the rule) and is
followed by "± SE" or by the words saying why there is none ("n/a (one layout)")."""
from __future__ import annotations

import re

BARE_DIFFERENCE = re.compile(r"(?<![\w.])\+\d+\.\d{3}(?! ± | n/a)")


def bare_differences(text: str) -> list[str]:
    """Each signed difference in ``text`` lacking its standard error, with 100 characters before it."""
    return [text[max(0, m.start() - 100): m.end() + 20] for m in BARE_DIFFERENCE.finditer(text)]
