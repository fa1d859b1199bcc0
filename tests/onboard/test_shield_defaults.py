"""ShieldParams' defaults are the on-board controller's: every field ``fillParams`` (firmware_app/src/
polycc_controller.c) sets from a constant or from a param's default is read from the C source, its macros
resolved from the headers, and compared with :class:`polycc.onboard.shield.ShieldParams`. Regression: the
controller's n_commit became 2 (two certified periods) while the Python mirror still said 1."""

from __future__ import annotations

import re
from dataclasses import fields
from pathlib import Path

import numpy as np

from polycc.onboard.shield import ShieldParams

SRC = Path(__file__).resolve().parents[2] / "firmware_app" / "src"
# fields set from a runtime param: the param's default macro (the scene's kappa and the eval budget excepted)
FROM_PARAM = {"radius": "POLYCC_SHIELD_DEFAULT_RADIUS", "tube": "POLYCC_SHIELD_DEFAULT_TUBE",
              "v_max": "POLYCC_SHIELD_DEFAULT_VMAX", "k1": "POLYCC_SHIELD_DEFAULT_K1",
              "k0": "POLYCC_SHIELD_DEFAULT_K0", "psi_cap": "POLYCC_SHIELD_DEFAULT_PSI_CAP"}
NOT_CONSTANT = {"kappa", "max_evals"}


def _macros() -> dict[str, str]:
    out = {}
    for h in ("polycc_controller.h", "polycc_shield.h"):
        for name, value in re.findall(r"^#define\s+(POLYCC_\w+)\s+([-0-9.eEfu]+)", (SRC / h).read_text(), re.M):
            out[name] = value
    return out


def _number(token: str, macros: dict[str, str]) -> float:
    token = macros.get(token, token)
    return float(token.rstrip("fu"))


def test_shield_params_defaults_are_the_controllers():
    body = re.search(r"static void fillParams\(polycc_shield_params_t \*q\)\s*\{(.*?)\n\}",
                     (SRC / "polycc_controller.c").read_text(), re.S).group(1)
    assigned = dict(re.findall(r"q->(\w+)\s*=\s*([^;]+);", body))
    macros = _macros()
    names = {f.name for f in fields(ShieldParams)}
    assert set(assigned) == names, f"fillParams sets {sorted(set(assigned) ^ names)} differently from ShieldParams"
    src = (SRC / "polycc_controller.c").read_text()
    for name, macro in FROM_PARAM.items():  # the param's variable starts at that default
        var = assigned[name].strip()
        assert re.search(rf"\b{var}\s*=\s*{macro}\b", src), f"{var} (q->{name}) does not start at {macro}"
    checked = 0
    for name in sorted(names - NOT_CONSTANT):
        expr = assigned[name].strip()
        token = FROM_PARAM[name] if name in FROM_PARAM else expr
        assert re.fullmatch(r"[A-Z_0-9]+|[-0-9.]+f?u?", token), f"{name} = {expr}: not a constant"
        want = _number(token, macros)
        got = getattr(ShieldParams(), name)
        assert np.float32(got) == np.float32(want), f"ShieldParams.{name} = {got}, the controller's is {want} ({token})"
        checked += 1
    assert checked == len(names) - len(NOT_CONSTANT)
