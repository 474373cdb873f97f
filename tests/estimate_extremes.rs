//! Noise-free extremes across the whole physical domain (sweep).

mod scene_common;

use irid::estimate::{Mode, Solver};
use irid::scene::Scene;
use irid::synth::scene_bands;
use irid::synth::Renderer;
use scene_common::with_known_angle;
use std::path::Path;

fn scene(n2: f64, pol: &str, known: bool) -> Scene {
    let text = format!(
        r#"
[ambient]
n = 1.0
[substrate]
n = 1.6
[film]
n = {n2}
[light]
polarization = "{pol}"
[bands]
start_nm = 400
stop_nm = 700
step_nm = 10
fwhm_nm = 0
[truth]
width = 31
height = 19
thickness_nm = {{ linear_x = [0.0, 3000.0] }}
angle_deg = {{ linear_y = [0.0, 89.5] }}
noise_sigma = 0.0
seed = 1
{}
"#,
        std::env::var("LEVEL")
            .map(|l| format!("[measurement]\nlevel = \"{l}\""))
            .unwrap_or_default()
    );
    let s: Scene = Scene::from_toml(&text, "<t>", Path::new(".")).unwrap();
    if known {
        with_known_angle(s)
    } else {
        s
    }
}

#[test]
#[ignore]
fn sweep() {
    let mut total = 0;
    for n2 in [1.01, 1.2, 1.37, 1.59] {
        for pol in ["s", "p", "u"] {
            for known in [true, false] {
                let s = scene(n2, pol, known);
                let bands = scene_bands(&s).unwrap();
                let r = Renderer::new(&s).unwrap();
                let cube = r.render_cube(&bands).unwrap();
                let truth = r.truth_maps(&bands);
                for mode in [Mode::Fast, Mode::Balanced, Mode::Accurate] {
                    let t0 = std::time::Instant::now();
                    let mut solver = Solver::new(&s, &bands, mode).unwrap();
                    let maps = solver.fit_cube(&cube).unwrap();
                    let mut wrong = vec![];
                    let mut valid = 0;
                    for i in 0..maps.width * maps.height {
                        if maps.valid[i] < 0.5 {
                            continue;
                        }
                        valid += 1;
                        let d = f64::from(truth.thickness_nm[i]);
                        let err = f64::from(maps.thickness_nm[i]) - d;
                        let tol = (3.0 * f64::from(maps.sigma_thickness_nm[i])).max(2.0);
                        if err.abs() > tol {
                            wrong.push(format!(
                                "d {d:.0} θ {:.1} est {:.1}±{:.2} θ̂ {:.2}",
                                truth.theta_deg[i],
                                maps.thickness_nm[i],
                                maps.sigma_thickness_nm[i],
                                maps.theta_deg[i]
                            ));
                        }
                    }
                    total += wrong.len();
                    eprintln!(
                        "n2 {n2} {pol} known {known} {mode:?}: valid {valid}/{} wrong {} ({:.1}s)",
                        maps.width * maps.height,
                        wrong.len(),
                        t0.elapsed().as_secs_f64()
                    );
                    for w in wrong.iter().take(6) {
                        eprintln!("    {w}");
                    }
                }
            }
        }
    }
    assert_eq!(total, 0);
}

#[test]
#[ignore]
fn one() {
    let n2: f64 = std::env::var("N2").unwrap().parse().unwrap();
    let pol = std::env::var("POL").unwrap();
    let known = std::env::var("KNOWN").is_ok();
    let s = scene(n2, &pol, known);
    let bands = scene_bands(&s).unwrap();
    let r = Renderer::new(&s).unwrap();
    let cube = r.render_cube(&bands).unwrap();
    let truth = r.truth_maps(&bands);
    let row: usize = std::env::var("ROW").unwrap().parse().unwrap();
    for mode in [Mode::Fast, Mode::Balanced, Mode::Accurate] {
        let mut solver = Solver::new(&s, &bands, mode).unwrap();
        let maps = solver.fit_cube(&cube).unwrap();
        let (l, m, why) = solver.level();
        eprintln!(
            "level {} {why} {l:?} noise {:?}",
            m.name(),
            solver.noise().map(|n| n.typical_sigma(0.05))
        );
        for x in 0..maps.width {
            let i = row * maps.width + x;
            eprintln!(
                "{mode:?} d {:.0} θ {:.2}: est {:.2}±{:.2} θ̂ {:.3}±{:.3} rms {:.2e} reason {}",
                truth.thickness_nm[i],
                truth.theta_deg[i],
                maps.thickness_nm[i],
                maps.sigma_thickness_nm[i],
                maps.theta_deg[i],
                maps.sigma_theta_deg[i],
                maps.residual_rms[i],
                maps.reason[i]
            );
        }
    }
}

#[test]
#[ignore]
fn dump() {
    let s = scene(1.59, "p", false);
    let bands = scene_bands(&s).unwrap();
    let r = Renderer::new(&s).unwrap();
    let cube = r.render_cube(&bands).unwrap();
    let n = cube.plane_len();
    let i = 10; // row 0, d = 1000
    let v: Vec<String> = (0..bands.len())
        .map(|b| format!("{:.6}", cube.data[b * n + i]))
        .collect();
    eprintln!("DUMP {}", v.join(" "));
}
