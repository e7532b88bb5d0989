"""C code for the compensation function of a calibration (``castimate codegen``).

From a ``results.json`` this module emits a self-contained C99 directory: the compensation
``raw (M triads x 6) -> out (M x 6)`` with

    f = T^-1 ((raw_acc - offset_acc) * scale_acc - b_acc)     (m/s^2, body frame)
    w = T_g^-1 ((raw_gyr - offset_gyr) * scale_gyr - b_gyr)   (rad/s, body frame)

where ``raw`` is in the data's units (counts if the results declare a counts conversion, else SI)
and ``T``, ``b`` are the results' (raw ≈ T f + b in SI). The math is built with CasADi SX and
emitted by CasADi's ``CodeGenerator``; a small hand-written API file wraps it:

- ``castimate_compensate(raw, out)``: the estimates baked in as constants;
- ``castimate_compensate_p(&params, raw, out)``: the parameters from a ``castimate_params`` struct
  (``castimate_params_default`` holds the estimates).

With the C sources come ``test_vectors.txt`` (random and edge-case raw samples with the outputs
computed here with numpy, independently of CasADi), ``test_main.c``, a ``Makefile`` whose
``check`` target builds everything and runs the vectors through both variants, and a README.
The output is deterministic: the same results file gives byte-identical files.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io.results import read_results
from ..io.units import UnitConversion, parse_units, si_units
from .ctext import c_comment, c_double, c_string, casadi_sources

#: The files written into the output directory, in this order.
API_C = "castimate_compensation.c"
API_H = "castimate_compensation.h"
CG_C = "castimate_cg.c"
CG_H = "castimate_cg.h"
FILES = (API_H, API_C, CG_C, CG_H, "test_main.c", "test_vectors.txt", "Makefile", "README.md")

#: Names of the CasADi-generated functions (called only from the API file).
CG_CONST = "castimate_cg_compensate_const"
CG_PARAM = "castimate_cg_compensate_param"

#: Doubles per sensor in the flat parameter vector: T_inv (9, row-major), b (3), scale (3), offset (3).
SENSOR_PARAMS = 18

#: Seed of the random test vectors (fixed: the output is deterministic).
SEED = 20240611
N_RANDOM = 300
TOLERANCE = 1e-9


@dataclass(frozen=True)
class Sensor:
    """One accelerometer or gyroscope triad: raw = T f + b in SI, SI = (raw - offset) * scale."""

    T: np.ndarray
    b: np.ndarray
    units: UnitConversion

    @property
    def T_inv(self) -> np.ndarray:
        return np.linalg.inv(self.T)

    def flat(self) -> np.ndarray:
        """The 18 doubles of this sensor in the parameter vector."""
        return np.concatenate([self.T_inv.reshape(9), self.b, self.units.scale, self.units.offset])

    def compensate(self, raw: np.ndarray) -> np.ndarray:
        """Reference compensation in numpy: (N, 3) raw -> (N, 3) SI, body frame (a linear solve, not T_inv)."""
        si = self.units.to_si(raw)
        return np.linalg.solve(self.T, (si - self.b).T).T


@dataclass(frozen=True)
class Calibration:
    """What the C code needs from a results file."""

    source: str
    sha256: str
    names: tuple[str, ...]
    acc: tuple[Sensor, ...]
    gyro: tuple[Sensor | None, ...]

    @property
    def m(self) -> int:
        return len(self.names)

    def compensate(self, raw: np.ndarray) -> np.ndarray:
        """Reference compensation of (N, 6M) raw samples -> (N, 6M) outputs, numpy only."""
        raw = np.atleast_2d(np.asarray(raw, float))
        out = np.zeros_like(raw)
        for i in range(self.m):
            out[:, 6 * i:6 * i + 3] = self.acc[i].compensate(raw[:, 6 * i:6 * i + 3])
            if self.gyro[i] is not None:
                out[:, 6 * i + 3:6 * i + 6] = self.gyro[i].compensate(raw[:, 6 * i + 3:6 * i + 6])
        return out


def load_calibration(path: str | Path) -> Calibration:
    """Read a results.json for code generation; a problem file gives an InputError saying to solve it first."""
    path = Path(path)
    if path.suffix.lower() in (".yaml", ".yml"):
        raise InputError(path, "", "the compensation function needs a results.json, not a problem file; solve it "
                                   f"first (castimate solve {path} -o DIR) and pass DIR/results.json")
    doc = read_results(path)
    units = doc.get("units", {})
    conv = {}
    for key, quantity in (("data_accelerometer", "accelerometer"), ("data_gyroscope", "gyroscope")):
        spec = units.get(key)
        conv[quantity] = (parse_units(spec, path, f"units.{key}", quantity) if spec is not None
                          else si_units(quantity))
    names, acc, gyro = [], [], []
    for name, t in doc["triads"].items():  # the results' order is the C array order
        names.append(str(name))
        a = t["accelerometer"]
        acc.append(Sensor(np.asarray(a["T"], float), np.asarray(a["b"], float), conv["accelerometer"]))
        g = t.get("gyroscope")
        gyro.append(None if g is None else Sensor(np.asarray(g["T"], float), np.asarray(g["b"], float),
                                                  conv["gyroscope"]))
    return Calibration(str(path), hashlib.sha256(path.read_bytes()).hexdigest(), tuple(names),
                       tuple(acc), tuple(gyro))


# ----------------------------------------------------------------------------------------------
# CasADi part


def _casadi_functions(cal: Calibration):
    """The two CasADi functions: constants baked in, and parameters as a flat input vector."""
    import casadi as ca

    m = cal.m
    raw = ca.SX.sym("raw", 6 * m)
    p = ca.SX.sym("p", 2 * SENSOR_PARAMS * m)

    def sensor_expr(r, T_inv, b, scale, offset):
        return ca.mtimes(T_inv, (r - offset) * scale - b)

    const_out, param_out = [], []
    for i in range(m):
        for k, sensor in enumerate((cal.acc[i], cal.gyro[i])):
            r = raw[6 * i + 3 * k:6 * i + 3 * k + 3]
            if sensor is None:
                const_out.append(ca.SX.zeros(3, 1))
            else:
                const_out.append(sensor_expr(r, ca.DM(sensor.T_inv), ca.DM(sensor.b),
                                             ca.DM(sensor.units.scale), ca.DM(sensor.units.offset)))
            q = p[(2 * i + k) * SENSOR_PARAMS:(2 * i + k + 1) * SENSOR_PARAMS]
            T_inv = ca.reshape(q[0:9], 3, 3).T  # row-major in C
            param_out.append(sensor_expr(r, T_inv, q[9:12], q[12:15], q[15:18]))
    f_const = ca.Function(CG_CONST, [raw], [ca.densify(ca.vertcat(*const_out))], ["raw"], ["out"])
    f_param = ca.Function(CG_PARAM, [p, raw], [ca.densify(ca.vertcat(*param_out))], ["p", "raw"], ["out"])
    return f_const, f_param


def _casadi_sources(cal: Calibration) -> tuple[str, str]:
    """CasADi's generated C file and header (no main, double, prefixed internals), as text."""
    return casadi_sources(_casadi_functions(cal), CG_C)


# ----------------------------------------------------------------------------------------------
# Hand-written C


def _units_line(u: UnitConversion) -> str:
    if u.is_identity:
        return f"SI ({u.si_unit}), no conversion"
    return (f"counts: SI = (raw - offset) * scale, scale = [{', '.join(f'{v:.9g}' for v in u.scale)}] "
            f"{u.si_unit}/count, offset = [{', '.join(f'{v:.9g}' for v in u.offset)}] counts")


def _triad_table(cal: Calibration) -> str:
    lines = []
    for i, name in enumerate(cal.names):
        g = "gyroscope calibrated" if cal.gyro[i] is not None else \
            "NO gyroscope in the calibration: its angular rate outputs are always 0"
        lines.append(f" *   {i}: {c_comment(name)} (raw[{6 * i}..{6 * i + 5}], out[{6 * i}..{6 * i + 5}]); {g}")
    return "\n".join(lines)


def _header(cal: Calibration) -> str:
    acc_u, gyro_u = cal.acc[0].units, next((g.units for g in cal.gyro if g is not None), None)
    return f"""/* castimate_compensation.h: compensation of a calibrated inertial sensor array.
 *
 * Generated by castimate codegen from {c_comment(Path(cal.source).name)}
 * (sha256 {cal.sha256}). Do not edit: regenerate instead.
 *
 * Array layout: one sample of all {cal.m} triads is an array of CASTIMATE_N_RAW = 6 * {cal.m} doubles,
 * triad after triad, each as ax ay az gx gy gz. The output has the same layout: per triad the
 * calibrated specific force fx fy fz (m/s^2) then the angular rate wx wy wz (rad/s), both in the
 * body frame.
 *
 * Input units (the units of the calibration data):
 *   accelerometer: {c_comment(_units_line(acc_u))}
 *   gyroscope:     {c_comment(_units_line(gyro_u)) if gyro_u is not None else "not calibrated"}
 *
 * Math, per triad and sensor: out = T_inv * ((raw - offset) * scale - b), where raw = T f + b
 * (SI) is the results' sensor model.
 *
 * Triads (index: name):
{_triad_table(cal)}
 *
 * Plain C99, no allocation, no global state: the functions are reentrant.
 */
#ifndef CASTIMATE_COMPENSATION_H
#define CASTIMATE_COMPENSATION_H

#ifdef __cplusplus
extern "C" {{
#endif

/** Number of triads. */
#define CASTIMATE_N_TRIADS {cal.m}
/** Doubles per raw sample: 6 per triad (ax ay az gx gy gz). */
#define CASTIMATE_N_RAW (6 * CASTIMATE_N_TRIADS)
/** Doubles per output sample: 6 per triad (fx fy fz wx wy wz). */
#define CASTIMATE_N_OUT (6 * CASTIMATE_N_TRIADS)

/** The parameters of one sensor triad (accelerometer or gyroscope). */
typedef struct {{
    double T_inv[9];  /**< inverse of T, row-major: out = T_inv * (si - b) */
    double b[3];      /**< bias, SI units (m/s^2 or rad/s) */
    double scale[3];  /**< unit conversion: si = (raw - offset) * scale; SI units per raw unit */
    double offset[3]; /**< unit conversion offset, raw units (0 for SI data) */
}} castimate_sensor_params;

/** The parameters of one triad. A triad without gyroscope has gyro.T_inv all 0 (rate output 0). */
typedef struct {{
    castimate_sensor_params acc;
    castimate_sensor_params gyro;
}} castimate_triad_params;

/** The parameters of the whole array, triad i at triad[i]. */
typedef struct {{
    castimate_triad_params triad[CASTIMATE_N_TRIADS];
}} castimate_params;

/** The estimates of the calibration (the same numbers castimate_compensate has baked in). */
extern const castimate_params castimate_params_default;

/** The triad names, in array order. */
extern const char *const castimate_triad_names[CASTIMATE_N_TRIADS];

/**
 * Compensate one raw sample with the estimates baked in as constants.
 * raw: CASTIMATE_N_RAW doubles in the input units above; out: CASTIMATE_N_OUT doubles (SI, body
 * frame). raw and out must not overlap. Returns 0 on success, non-zero on error.
 */
int castimate_compensate(const double *raw, double *out);

/**
 * Compensate one raw sample with the parameters in *p (e.g. &castimate_params_default or a copy
 * with updated values). Same layout, units and return value as castimate_compensate.
 */
int castimate_compensate_p(const castimate_params *p, const double *raw, double *out);

#ifdef __cplusplus
}} /* extern "C" */
#endif

#endif /* CASTIMATE_COMPENSATION_H */
"""


def _sensor_init(s: Sensor | None, indent: str) -> str:
    if s is None:
        vals = [np.zeros(9), np.zeros(3), np.ones(3), np.zeros(3)]
    else:
        vals = [s.T_inv.reshape(9), s.b, s.units.scale, s.units.offset]
    parts = [", ".join(c_double(v) for v in arr) for arr in vals]
    return (f"{{\n{indent}    {{{parts[0]}}},\n{indent}    {{{parts[1]}}},\n"
            f"{indent}    {{{parts[2]}}},\n{indent}    {{{parts[3]}}}\n{indent}}}")


def _api_source(cal: Calibration) -> str:
    inits = []
    for i, name in enumerate(cal.names):
        note = "" if cal.gyro[i] is not None else " (no gyroscope: T_inv 0, rate output 0)"
        inits.append(f"        /* {i}: {c_comment(name)}{note} */\n        {{\n            "
                     f"{_sensor_init(cal.acc[i], '            ')},\n            "
                     f"{_sensor_init(cal.gyro[i], '            ')}\n        }}")
    names = ",\n    ".join(c_string(n) for n in cal.names)
    triads = ",\n".join(inits)
    return f"""/* castimate_compensation.c: the API of castimate_compensation.h around the CasADi-generated
 * castimate_cg.c. Generated by castimate codegen from {c_comment(Path(cal.source).name)}
 * (sha256 {cal.sha256}). Do not edit: regenerate instead.
 */
#include "castimate_compensation.h"
#include "castimate_cg.h"

#define CASTIMATE_SENSOR_PARAMS {SENSOR_PARAMS}
#define CASTIMATE_N_PARAMS (2 * CASTIMATE_SENSOR_PARAMS * CASTIMATE_N_TRIADS)

const char *const castimate_triad_names[CASTIMATE_N_TRIADS] = {{
    {names}
}};

const castimate_params castimate_params_default = {{
    {{
{triads}
    }}
}};

int castimate_compensate(const double *raw, double *out)
{{
    const casadi_real *arg[{CG_CONST}_SZ_ARG];
    casadi_real *res[{CG_CONST}_SZ_RES];
    casadi_int iw[{CG_CONST}_SZ_IW + 1];
    casadi_real w[{CG_CONST}_SZ_W + 1];
    if (raw == 0 || out == 0) return 1;
    arg[0] = raw;
    res[0] = out;
    return {CG_CONST}(arg, res, iw, w, 0);
}}

/* Copy one sensor's parameters to the flat vector layout of the generated function. */
static double *castimate_pack(const castimate_sensor_params *s, double *q)
{{
    int k;
    for (k = 0; k < 9; ++k) *q++ = s->T_inv[k];
    for (k = 0; k < 3; ++k) *q++ = s->b[k];
    for (k = 0; k < 3; ++k) *q++ = s->scale[k];
    for (k = 0; k < 3; ++k) *q++ = s->offset[k];
    return q;
}}

int castimate_compensate_p(const castimate_params *p, const double *raw, double *out)
{{
    double flat[CASTIMATE_N_PARAMS];
    double *q = flat;
    const casadi_real *arg[{CG_PARAM}_SZ_ARG];
    casadi_real *res[{CG_PARAM}_SZ_RES];
    casadi_int iw[{CG_PARAM}_SZ_IW + 1];
    casadi_real w[{CG_PARAM}_SZ_W + 1];
    int i;
    if (p == 0 || raw == 0 || out == 0) return 1;
    for (i = 0; i < CASTIMATE_N_TRIADS; ++i) {{
        q = castimate_pack(&p->triad[i].acc, q);
        q = castimate_pack(&p->triad[i].gyro, q);
    }}
    arg[0] = flat;
    arg[1] = raw;
    res[0] = out;
    return {CG_PARAM}(arg, res, iw, w, 0);
}}
"""


TEST_MAIN = r"""/* test_main.c: run test_vectors.txt through both variants of castimate_compensation.h.
 * Usage: castimate_test [test_vectors.txt]. Exits 0 if every output is within
 * TOL * max(1, |expected|) of the expected value, 1 on a mismatch, 2 on a bad file.
 * Generated by castimate codegen. Do not edit: regenerate instead.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>

#include "castimate_compensation.h"

#define TOL 1e-9

/* Skip white space and '#' comment lines; returns the next character (not consumed) or EOF. */
static int skip_comments(FILE *f)
{
    int c;
    for (;;) {
        c = fgetc(f);
        while (c == ' ' || c == '\t' || c == '\r' || c == '\n') c = fgetc(f);
        if (c == '#') {
            while (c != '\n' && c != EOF) c = fgetc(f);
            continue;
        }
        if (c != EOF) ungetc(c, f);
        return c;
    }
}

static int compare(const char *variant, long sample, const double *got, const double *want,
                   double *max_abs, double *max_rel)
{
    int i, bad = 0;
    for (i = 0; i < CASTIMATE_N_OUT; ++i) {
        double d = fabs(got[i] - want[i]);
        double r = d / (fabs(want[i]) > 1.0 ? fabs(want[i]) : 1.0);
        if (!(d <= *max_abs)) *max_abs = d;
        if (!(r <= *max_rel)) *max_rel = r;
        if (!(r <= TOL)) {
            if (bad == 0)
                fprintf(stderr, "%s: sample %ld, output %d: got %.17g, expected %.17g\n",
                        variant, sample, i, got[i], want[i]);
            bad = 1;
        }
    }
    return bad;
}

int main(int argc, char **argv)
{
    const char *path = argc > 1 ? argv[1] : "test_vectors.txt";
    FILE *f = fopen(path, "r");
    long m, n, s;
    int i, failures = 0;
    double raw[CASTIMATE_N_RAW], want[CASTIMATE_N_OUT], out_a[CASTIMATE_N_OUT], out_b[CASTIMATE_N_OUT];
    double max_abs = 0.0, max_rel = 0.0;
    if (f == NULL) {
        fprintf(stderr, "%s: cannot open\n", path);
        return 2;
    }
    skip_comments(f);
    if (fscanf(f, "%ld %ld", &m, &n) != 2 || m != CASTIMATE_N_TRIADS || n < 1) {
        fprintf(stderr, "%s: expected a line 'TRIADS SAMPLES' with TRIADS = %d\n", path, CASTIMATE_N_TRIADS);
        fclose(f);
        return 2;
    }
    for (s = 0; s < n; ++s) {
        skip_comments(f);
        for (i = 0; i < CASTIMATE_N_RAW; ++i)
            if (fscanf(f, "%lf", &raw[i]) != 1) goto bad_file;
        for (i = 0; i < CASTIMATE_N_OUT; ++i)
            if (fscanf(f, "%lf", &want[i]) != 1) goto bad_file;
        if (castimate_compensate(raw, out_a) != 0 || castimate_compensate_p(&castimate_params_default, raw, out_b) != 0) {
            fprintf(stderr, "sample %ld: a compensation function returned an error\n", s);
            failures++;
            continue;
        }
        failures += compare("castimate_compensate", s, out_a, want, &max_abs, &max_rel);
        failures += compare("castimate_compensate_p", s, out_b, want, &max_abs, &max_rel);
    }
    fclose(f);
    printf("samples: %ld, triads: %ld, variants: 2\n", n, m);
    printf("max abs difference: %.3e\n", max_abs);
    printf("max rel difference: %.3e (tolerance %.0e relative to max(1, |expected|))\n", max_rel, TOL);
    if (failures) {
        printf("FAILED: %d mismatching sample outputs\n", failures);
        return 1;
    }
    printf("OK\n");
    return 0;

bad_file:
    fprintf(stderr, "%s: sample %ld: expected %d raw then %d expected numbers\n", path, s,
            CASTIMATE_N_RAW, CASTIMATE_N_OUT);
    fclose(f);
    return 2;
}
"""


MAKEFILE = """\
# Build and check the castimate compensation code. Generated by castimate codegen.
#   make          build castimate_compensation.o, castimate_cg.o and the test program
#   make check    build, then run test_vectors.txt through both variants (non-zero exit on mismatch)
#   make clean    remove the build products
CC ?= gcc
# make's built-in default CC is cc; use gcc unless CC comes from the environment or command line.
ifeq ($(origin CC),default)
CC = gcc
endif
CFLAGS = -std=c99 -O2 -Wall -Wextra -Werror
# castimate_cg.c is CasADi's generated code: its fixed calling convention passes work arrays and a
# memory index that simple functions do not use, which -Wextra reports as unused parameters. That
# one warning is switched off for that one file; everything else compiles with the strict CFLAGS.
CG_CFLAGS = $(CFLAGS) -Wno-unused-parameter
LDLIBS = -lm

OBJS = castimate_compensation.o castimate_cg.o

all: $(OBJS) castimate_test

castimate_cg.o: castimate_cg.c castimate_cg.h
\t$(CC) $(CG_CFLAGS) -c castimate_cg.c -o $@

castimate_compensation.o: castimate_compensation.c castimate_compensation.h castimate_cg.h
\t$(CC) $(CFLAGS) -c castimate_compensation.c -o $@

test_main.o: test_main.c castimate_compensation.h
\t$(CC) $(CFLAGS) -c test_main.c -o $@

castimate_test: test_main.o $(OBJS)
\t$(CC) $(CFLAGS) -o $@ test_main.o $(OBJS) $(LDLIBS)

check: castimate_test test_vectors.txt
\t./castimate_test test_vectors.txt

clean:
\trm -f $(OBJS) test_main.o castimate_test

.PHONY: all check clean
"""


def _readme(cal: Calibration, n_vectors: int) -> str:
    acc_u, gyro_u = cal.acc[0].units, next((g.units for g in cal.gyro if g is not None), None)
    rows = "\n".join(f"| {i} | {n} | {6 * i}..{6 * i + 5} | {'yes' if cal.gyro[i] is not None else 'no (rate output 0)'} |"
                     for i, n in enumerate(cal.names))
    return f"""# castimate compensation code

Generated by `castimate codegen` from `{cal.source}`
(sha256 `{cal.sha256}`). Do not edit: regenerate instead. Plain C99; no CasADi at run time.

## Build

```
make          # objects and the test program (CC ?= gcc, CFLAGS = -std=c99 -O2 -Wall -Wextra -Werror)
make check    # run test_vectors.txt ({n_vectors} samples) through both variants; non-zero exit on mismatch
make clean
```

To use it elsewhere, compile `castimate_compensation.c` and `castimate_cg.c` with your project and
include `castimate_compensation.h` (link with `-lm`). `castimate_cg.c` is CasADi's generated code;
it needs `-Wno-unused-parameter` under `-Wextra -Werror` (its calling convention passes work
arrays that these simple functions do not use). The other files compile with the strict flags.

## API (`castimate_compensation.h`)

- `int castimate_compensate(const double *raw, double *out)`: the estimates baked in as constants.
- `int castimate_compensate_p(const castimate_params *p, const double *raw, double *out)`: the
  parameters from a struct; `castimate_params_default` holds the estimates (same numbers).
  Per triad and sensor (`p->triad[i].acc`, `p->triad[i].gyro`): `T_inv[9]` (row-major),
  `b[3]` (SI), `scale[3]` and `offset[3]` (unit conversion `si = (raw - offset) * scale`).
- Both return 0 on success. No allocation, no global state.

## Units and array layout

One sample is `CASTIMATE_N_RAW = 6 x {cal.m}` doubles, triad after triad, each `ax ay az gx gy gz`,
in the units of the calibration data:

- accelerometer: {_units_line(acc_u)}
- gyroscope: {_units_line(gyro_u) if gyro_u is not None else "not calibrated"}

The output has the same layout: per triad `fx fy fz` (specific force, m/s^2) then `wx wy wz`
(angular rate, rad/s), in the body frame:
`out = T^-1 ((raw - offset) * scale - b)`, with raw ≈ T f + b (SI) the calibration's sensor model.

| index | triad | raw / out elements | gyroscope |
|---|---|---|---|
{rows}

## Test vectors

`test_vectors.txt`: after `#` comment lines, a line `TRIADS SAMPLES`, then one line per sample with
the {6 * cal.m} raw values followed by the {6 * cal.m} expected outputs (`%.17g`), computed by castimate
with numpy (a linear solve), independently of the CasADi code. `test_main.c` accepts a difference
of at most {TOLERANCE:g} x max(1, |expected|).
"""


# ----------------------------------------------------------------------------------------------
# Test vectors


def _raw_samples(cal: Calibration) -> np.ndarray:
    """Deterministic raw samples: edge cases, then N_RANDOM plausible random samples."""
    rng = np.random.default_rng(SEED)
    m = cal.m

    def to_raw(s: Sensor | None, si_body: np.ndarray, fallback_units: UnitConversion) -> np.ndarray:
        u = s.units if s is not None else fallback_units
        si = si_body @ s.T.T + s.b if s is not None else si_body
        return si / u.scale + u.offset

    gyro_fallback = next((g.units for g in cal.gyro if g is not None), None)
    rows = []
    # Edge cases: zero, the unit offsets (0 SI), the biases (0 out), large and negative values.
    rows.append(np.zeros(6 * m))
    for special in ("offset", "bias", "big", "neg"):
        r = np.zeros(6 * m)
        for i in range(m):
            for k, s in enumerate((cal.acc[i], cal.gyro[i])):
                u = s.units if s is not None else (gyro_fallback or cal.acc[i].units)
                if special == "offset":
                    v = u.offset
                elif special == "bias":
                    v = (s.b / u.scale + u.offset) if s is not None else u.offset
                elif special == "big":
                    v = u.offset + np.array([1.0, -1.0, 1.0]) * (160.0 if k == 0 else 35.0) / np.abs(u.scale)
                else:
                    v = -np.abs(u.offset) - np.array([1.0, 2.0, 3.0]) * (20.0 if k == 0 else 5.0) / np.abs(u.scale)
                r[6 * i + 3 * k:6 * i + 3 * k + 3] = v
        rows.append(r)
    for _ in range(N_RANDOM):
        r = np.zeros(6 * m)
        g_dir = rng.normal(size=3)
        g_dir *= 9.81 / np.linalg.norm(g_dir)
        for i in range(m):
            f = g_dir + rng.uniform(-5.0, 5.0, 3)
            w = rng.uniform(-6.0, 6.0, 3)
            r[6 * i:6 * i + 3] = to_raw(cal.acc[i], f, cal.acc[i].units)
            gu = gyro_fallback or cal.acc[i].units
            r[6 * i + 3:6 * i + 6] = to_raw(cal.gyro[i], w, gu)
        rows.append(r)
    raw = np.array(rows)
    # Counts data are integers; keep them so (rounding is part of the determinism, not the math).
    for i in range(m):
        for k, s in enumerate((cal.acc[i], cal.gyro[i])):
            u = s.units if s is not None else None
            if u is not None and not u.is_identity:
                raw[5:, 6 * i + 3 * k:6 * i + 3 * k + 3] = np.round(raw[5:, 6 * i + 3 * k:6 * i + 3 * k + 3])
    return raw


def test_vectors(cal: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """(raw, expected): raw samples and their compensation computed with numpy only."""
    raw = _raw_samples(cal)
    return raw, cal.compensate(raw)


def _vectors_text(cal: Calibration, raw: np.ndarray, expected: np.ndarray) -> str:
    lines = [
        "# castimate compensation test vectors (castimate codegen).",
        f"# source: {Path(cal.source).name} sha256 {cal.sha256}",
        "# Format: a line 'TRIADS SAMPLES', then per sample one line: the raw values (per triad",
        "# ax ay az gx gy gz, input units) followed by the expected outputs (per triad fx fy fz in",
        "# m/s^2 then wx wy wz in rad/s, body frame), computed with numpy independently of CasADi.",
        f"# triads: {', '.join(cal.names)}",
        f"{cal.m} {len(raw)}",
    ]
    for r, e in zip(raw, expected):
        lines.append(" ".join("%.17g" % v for v in np.concatenate([r, e])))
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------------------------
# Entry point


def generate_files(results_path: str | Path) -> dict[str, str]:
    """The emitted files as {name: text}, without writing anything."""
    cal = load_calibration(results_path)
    cg_c, cg_h = _casadi_sources(cal)
    raw, expected = test_vectors(cal)
    files = {
        API_H: _header(cal),
        API_C: _api_source(cal),
        CG_C: cg_c,
        CG_H: cg_h,
        "test_main.c": TEST_MAIN,
        "test_vectors.txt": _vectors_text(cal, raw, expected),
        "Makefile": MAKEFILE,
        "README.md": _readme(cal, len(raw)),
    }
    assert tuple(files) == FILES
    return files


__all__ = ["Calibration", "Sensor", "generate_files", "load_calibration", "test_vectors"]
