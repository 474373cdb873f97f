//! One grid interval's residual as a polynomial in the interval's
//! parameter `t` (degree 6: the squared residual of a cubic Hermite
//! interpolant), and its lowest point on `[0, 1]`.

/// `Σ (e − c1 t − c2 t² − c3 t³)²` as a polynomial in `t`, lowest power
/// first, from `Σe²`, `Σe·c1`, `Σe·c2`, `Σe·c3` and the interval's cross
/// sums `[Σc1², Σc1c2, Σc1c3, Σc2², Σc2c3, Σc3²]`.
pub(super) fn residual_poly(ee: f64, e1: f64, e2: f64, e3: f64, g: &[f64; 6]) -> [f64; 7] {
    let [s11, s12, s13, s22, s23, s33] = *g;
    [
        ee,
        -2.0 * e1,
        s11 - 2.0 * e2,
        2.0 * s12 - 2.0 * e3,
        s22 + 2.0 * s13,
        2.0 * s23,
        s33,
    ]
}

/// Value, first and second derivative of a polynomial (lowest power first).
pub(super) fn poly_eval(p: &[f64; 7], t: f64) -> (f64, f64, f64) {
    let (mut v, mut d1, mut d2) = (0.0, 0.0, 0.0);
    for &c in p.iter().rev() {
        d2 = d2 * t + 2.0 * d1;
        d1 = d1 * t + v;
        v = v * t + c;
    }
    (v, d1, d2)
}

/// The lowest point of polynomial `p` on `[0, 1]`. On one grid interval
/// the residual is close to a parabola: Newton from the vertex of the
/// parabola through `t = 0, ½, 1` converges in a few steps; where it does
/// not (no upward curvature, or it leaves the interval), safeguarded
/// Newton inside the bracket around the best of five samples. The ends
/// are candidates too.
pub(super) fn poly_min(p: &[f64; 7]) -> (f64, f64) {
    let (v0, v1) = (p[0], p.iter().sum::<f64>());
    let vh = poly_eval(p, 0.5).0;
    let ends = if v1 < v0 { (1.0, v1) } else { (0.0, v0) };
    let curv = v0 + v1 - 2.0 * vh;
    if curv > 0.0 {
        let mut t = (0.5 + 0.25 * (v0 - v1) / curv).clamp(0.0, 1.0);
        for _ in 0..10 {
            let (_, d1, d2) = poly_eval(p, t);
            // No upward curvature (or NaN): leave it to the fallback.
            if d2.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
                break;
            }
            let nt = t - d1 / d2;
            if !(0.0..=1.0).contains(&nt) {
                break;
            }
            // Newton converges quadratically: after a step under 1e-6
            // the new point is within ~1e-12 of the minimum (a step of
            // 1e-10 took one more evaluation for nothing).
            if (nt - t).abs() < 1e-6 {
                let v = poly_eval(p, nt).0;
                return if v <= ends.1 { (nt, v) } else { ends };
            }
            t = nt;
        }
    }
    poly_min_bracketed(p, ends)
}

/// [`poly_min`]'s fallback: the best of nine samples (or an end), then
/// safeguarded Newton on `p′` between its neighbours (bisection where a
/// Newton step would leave the bracket). A sample below both neighbours
/// has a stationary point between them.
pub(super) fn poly_min_bracketed(p: &[f64; 7], ends: (f64, f64)) -> (f64, f64) {
    let mut best = ends;
    for i in 1..8 {
        let t = i as f64 / 8.0;
        let v = poly_eval(p, t).0;
        if v < best.1 {
            best = (t, v);
        }
    }
    let (mut a, mut c) = ((best.0 - 0.125f64).max(0.0), (best.0 + 0.125f64).min(1.0));
    let mut t = best.0;
    for _ in 0..60 {
        let (_, d1, d2) = poly_eval(p, t);
        if d1 < 0.0 {
            a = t;
        } else {
            c = t;
        }
        let newton = t - d1 / d2;
        let nt = if d2 > 0.0 && newton > a && newton < c {
            newton
        } else {
            0.5 * (a + c)
        };
        let done = (nt - t).abs() < 1e-10 || c - a < 1e-10;
        t = nt;
        if done {
            break;
        }
    }
    let v = poly_eval(p, t).0;
    if v <= best.1 {
        (t, v)
    } else {
        best
    }
}
