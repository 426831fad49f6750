"""Build the curvature law kappa(thickness, transverse spacing, side) as a CSV table for
inverse/thickness_law.py: by forward simulation of ribbon patches (--model sim) or from the
coverage-blended strip model (--model strip). Options and output: validation.law_tables.
On a terminal, a status line on stderr counts the simulated patches and the time left
(selfshape.progress; -q hides it).

    python studies/thickness_law_sim.py --model strip
    python studies/thickness_law_sim.py --model sim --thickness 0.4 0.8 --spacing 4 8 \
        --sides front --mesh-size 3 --out out/law.csv
"""
from selfshape.progress import StatusLine
from validation.law_tables import main

if __name__ == "__main__":
    raise SystemExit(main(status=lambda enabled: StatusLine.for_stderr("thickness_law_sim", enabled)))
