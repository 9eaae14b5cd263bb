#!/usr/bin/env bash
# Demo of wrench recovery: simulate wind-off and wind-on tensions on the flat prototype rig with
# `cdpr solve`, recover the aerodynamic load with `cdpr wrench` (tare and absolute methods, with
# standard deviations and coefficients), then import a CASPR robot and solve on it.
set -euo pipefail
VENV=${VENV:-.venv}
OUT=${OUT:-out}
CDPR="$VENV/bin/cdpr"
RIG=data_samples/flat_optimum.toml
D="$OUT/wrench_demo"
mkdir -p "$D"
show() {  # selected columns of a CSV, rounded
    "$VENV/bin/python" - "$@" <<'PY'
import sys
import pandas as pd
df = pd.read_csv(sys.argv[1], comment="#")
cols = [c for c in sys.argv[2].split(",") if c in df.columns] if len(sys.argv) > 2 else list(df.columns)
print(df[cols].to_string(index=False, float_format=lambda v: f"{v:.4g}"))
PY
}

# three test points: level, pitched 2 deg, yawed 0.5 deg (the rig's reference position)
cat > "$D/poses.csv" <<CSV
label,x_m,y_m,z_m,roll_rad,pitch_rad,yaw_rad
level,0.5,0,0.335,0,0,0
pitch2,0.5,0,0.335,0,0.0349066,0
yaw05,0.5,0,0.335,0,0,0.00872665
CSV
# the "true" aerodynamic load at P, {O} axes, the same at every pose: 2.5 N drag, 4 N lift
cat > "$D/aero_true.csv" <<CSV
fx_N,fy_N,fz_N,mx_Nm,my_Nm,mz_Nm
2.5,0.1,4.0,0.001,0.01,-0.002
CSV
echo "== simulated tensions (exact distribution): wind off, then wind on with the load above"
"$CDPR" solve --rig "$RIG" --poses "$D/poses.csv" --method exact --out "$D/T0.csv"
"$CDPR" solve --rig "$RIG" --poses "$D/poses.csv" --wrench "$D/aero_true.csv" --method exact \
    --out "$D/Tw.csv"
echo
echo "== tare method (paper eq. 7), 0.05 N load cells, 0.5 mm / 0.1 deg pose noise, coefficients"
"$CDPR" wrench --rig "$RIG" --poses "$D/poses.csv" --tensions "$D/Tw.csv" --tare "$D/T0.csv" \
    --airspeed-mps 25.51 --pressure-Pa 101325 --temperature-K 293.15 \
    --area-m2 0.0174 --span-m 0.2441 --chord-m 0.0713 --out "$D/wrench_tare.csv"
show "$D/wrench_tare.csv" label,fx_N,fz_N,my_Nm,sd_fx_N,sd_fz_N,sd_my_Nm
show "$D/wrench_tare.csv" label,aoa_rad,sideslip_rad,CD,CY,CL,Cm,sd_CD,sd_CL,sd_Cm
echo
echo "== absolute method (mass model), same noise: the pose error on the pretension dominates"
"$CDPR" wrench --rig "$RIG" --poses "$D/poses.csv" --tensions "$D/Tw.csv" \
    --out "$D/wrench_absolute.csv"
show "$D/wrench_absolute.csv" label,fx_N,fz_N,my_Nm,sd_fx_N,sd_fz_N,sd_my_Nm
echo
echo "== a robot from another lab: CASPR's CoGiRo model imported and solved"
"$CDPR" rig import-caspr data_samples/caspr/CoGiRo_bodies.xml --out "$D/cogiro.toml"
"$CDPR" solve --rig "$D/cogiro.toml" --method exact --out "$D/cogiro_tensions.csv"
show "$D/cogiro_tensions.csv" "$(printf 'T_cable_%d_N,' 1 2 3 4 5 6 7 8)feasible"
