#!/usr/bin/env python3
"""Do the tests catch a wrong estimator? Each mutant below is one wrong factor or dropped term in
the renderer or a gradient; for each, the whole Rust suite runs against a copy of the tree that has
it, and the tests that fail are listed (docs/validation.md, "Checked by mutants").

    python3 scripts/mutants.py            # every mutant: about 5.5 min each on 2 cores
    python3 scripts/mutants.py M2 R4      # some

The copy is a git worktree of HEAD in a temporary folder, built in a target directory of its own
(seeded from ./target, so only volgrad itself is rebuilt); the repository is not touched.
"""
import os
import shutil
import subprocess
import sys
import tempfile

# (tag, what is wrong, file, text, its mutant): each text occurs once in its file.
MUTANTS = [
    ("M1", "joint's suffix weight without its 1/K", "src/gradient/adjoint.rs",
     "plan[j].weight = total / (k as f32 * p);", "plan[j].weight = total / p;"),
    ("M2", "joint without its transmittance part", "src/gradient/adjoint.rs",
     "segment.throughput * (h_probe - replayed.h_end) * replayed.length",
     "segment.throughput * h_probe * replayed.length"),
    ("M3", "a NEE shadow ray's term without its length", "src/gradient/adjoint.rs",
     "-shadow.contribution * length, sink", "-shadow.contribution, sink"),
    ("M4", "DRT's scattering part with W clamped at 1", "src/gradient/adjoint.rs",
     "segment.throughput * h * w, sink", "segment.throughput * h * w.min(1.0), sink"),
    ("M5", "the carried radiance with Russian roulette's 1/q clamped at 1", "src/gradient/adjoint.rs",
     "albedo * (nee + continuation_weight * deeper)",
     "albedo * (nee + continuation_weight.min(1.0) * deeper)"),
    ("M6", "alpha's gradient with the square root of T", "src/gradient/alpha_gradient.rs",
     "Vec3::splat(tr * stratum)", "Vec3::splat(tr.sqrt() * stratum)"),
    ("M7", "the albedo gradient without the emission term", "src/gradient/albedo_gradient.rs",
     "segment.throughput * (scattered - emitted)", "segment.throughput * scattered + emitted * 0.0"),
    ("M8", "one-light NEE's 1/P clamped at 1.5", "src/render/path.rs",
     "unoccluded * (total / w);", "unoccluded * (total / w).min(1.5);"),
    ("M9", "the emission gradient with (1 - albedo/2)", "src/gradient/emission_gradient.rs",
     "(Vec3::ONE - medium.albedo.at(p)) * d_radiance", "(Vec3::ONE - 0.5 * medium.albedo.at(p)) * d_radiance"),
    ("M10", "a trilinear splat giving each corner its mirror's weight", "src/gradient/adjoint.rs",
     "let (g, h) = (Vec3::ONE - f, f);", "let (g, h) = (f, Vec3::ONE - f);"),
    ("R1", "ratio tracking's Russian roulette going on at 0.9 of its weight", "src/volume/tracking.rs",
     "        *tr = RR_BELOW;\n", "        *tr = RR_BELOW * 0.9;\n"),
    ("R2", "delta tracking accepting 1.1 times too often", "src/volume/tracking.rs",
     "rng.gen::<f32>() * sigma_max < medium.sigma_t(ray.at(t))",
     "rng.gen::<f32>() * sigma_max < 1.1 * medium.sigma_t(ray.at(t))"),
    ("R3", "the environment's NEE MIS weight floored at 0.5", "src/render/path.rs",
     "power_heuristic(light_pdf, phase_pdf) / light_pdf", "power_heuristic(light_pdf, phase_pdf).max(0.5) / light_pdf"),
    ("R4", "an escaped path's MIS weight floored at 0.5", "src/render/path.rs",
     "power_heuristic(pdf, env.pdf(dir)))", "power_heuristic(pdf, env.pdf(dir)).max(0.5))"),
    ("R5", "a path's Russian-roulette weight capped at 2", "src/render/path.rs",
     "            1.0 / survive\n", "            1.0 / survive.max(0.5)\n"),
    ("R6", "the exposure's gradient without the composited background", "src/optimize/iteration.rs",
     "d.dot(*c - exposure * background(p))", "d.dot(*c - 0.0 * exposure * background(p))"),
    ("R7", "the exposure's gradient from one half of the render (biased by its variance)",
     "src/optimize/iteration.rs",
     "0.5 * (dot(&adjoint_of(a).1, b) + dot(&adjoint_of(b).1, a))",
     "0.5 * (dot(&adjoint_of(a).1, a) + dot(&adjoint_of(b).1, b))"),
]


def run(cmd, cwd, env=None):
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)


def main():
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    wanted = set(sys.argv[1:])
    scratch = tempfile.mkdtemp(prefix="volgrad-mutants-")
    tree, target = os.path.join(scratch, "tree"), os.path.join(scratch, "target")
    try:
        run(["git", "worktree", "add", "--detach", tree, "HEAD"], repo).check_returncode()
        if os.path.isdir(os.path.join(repo, "target")):
            run(["cp", "-a", os.path.join(repo, "target"), target], repo).check_returncode()
        env = dict(os.environ, CARGO_TARGET_DIR=target)
        for tag, what, path, text, mutant in MUTANTS:
            if wanted and tag not in wanted:
                continue
            file = os.path.join(tree, path)
            source = open(file).read()
            if source.count(text) != 1:
                sys.exit(f"{tag}: the text to mutate is not in {path} exactly once; update the list")
            open(file, "w").write(source.replace(text, mutant))
            build = run(["cargo", "build", "--release", "--tests"], tree, env)
            if build.returncode != 0:
                print(f"{tag} {what}: does not build\n{build.stderr[-1500:]}", flush=True)
            else:
                tests = run(["cargo", "test", "--release", "--no-fail-fast"], tree, env)
                failed = [line[5:-10] for line in tests.stdout.splitlines()
                          if line.startswith("test ") and line.endswith(" ... FAILED")]
                print(f"{tag} {what}: {len(failed)} tests failed", flush=True)
                for name in failed:
                    print(f"    {name}", flush=True)
            open(file, "w").write(source)
    finally:
        run(["git", "worktree", "remove", "--force", tree], repo)
        shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
