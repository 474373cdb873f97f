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

/// The value of `p` at `t` by Estrin's scheme: the powers `t²`, `t⁴` and
/// the pairs are independent, so the chain of dependent multiply–adds is
/// three long instead of Horner's six (Newton's steps below wait on each
/// evaluation in turn).
#[inline(always)]
fn value(p: &[f64; 7], t: f64) -> f64 {
    let (t2, t4) = (t * t, t * t * t * t);
    (p[0] + p[1] * t) + t2 * (p[2] + p[3] * t) + t4 * ((p[4] + p[5] * t) + t2 * p[6])
}

/// The first and second derivatives of a degree-6 polynomial, as their
/// own coefficients (lowest power first), for [`Derivatives::at`].
struct Derivatives {
    d1: [f64; 6],
    d2: [f64; 5],
}

impl Derivatives {
    #[inline(always)]
    fn of(p: &[f64; 7]) -> Derivatives {
        Derivatives {
            d1: [
                p[1],
                2.0 * p[2],
                3.0 * p[3],
                4.0 * p[4],
                5.0 * p[5],
                6.0 * p[6],
            ],
            d2: [
                2.0 * p[2],
                6.0 * p[3],
                12.0 * p[4],
                20.0 * p[5],
                30.0 * p[6],
            ],
        }
    }

    /// `(p′(t), p″(t))`, each by Estrin's scheme (see [`value`]).
    #[inline(always)]
    fn at(&self, t: f64) -> (f64, f64) {
        let (a, b) = (&self.d1, &self.d2);
        let (t2, t4) = (t * t, t * t * t * t);
        (
            (a[0] + a[1] * t) + t2 * (a[2] + a[3] * t) + t4 * (a[4] + a[5] * t),
            (b[0] + b[1] * t) + t2 * (b[2] + b[3] * t) + t4 * b[4],
        )
    }
}

/// The lowest point of polynomial `p` on `[0, 1]`. On one grid interval
/// the residual is close to a parabola: Newton from the vertex of the
/// parabola through `t = 0, ½, 1` converges in a few steps; where it does
/// not (no upward curvature, or it leaves the interval), safeguarded
/// Newton inside the bracket around the best of five samples. The ends
/// are candidates too.
pub(super) fn poly_min(p: &[f64; 7]) -> (f64, f64) {
    let (v0, v1) = (p[0], p.iter().sum::<f64>());
    let vh = value(p, 0.5);
    let ends = if v1 < v0 { (1.0, v1) } else { (0.0, v0) };
    let curv = v0 + v1 - 2.0 * vh;
    if curv > 0.0 {
        let slopes = Derivatives::of(p);
        let mut t = (0.5 + 0.25 * (v0 - v1) / curv).clamp(0.0, 1.0);
        for _ in 0..10 {
            let (d1, d2) = slopes.at(t);
            // No upward curvature (or NaN): leave it to the fallback.
            if d2.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
                break;
            }
            let nt = t - d1 / d2;
            if !(0.0..=1.0).contains(&nt) {
                break;
            }
            // Newton converges quadratically: after a step under 1e-3
            // the new point is within ~K·1e-6 of the minimum (K = |p‴/2p″|,
            // below 1 on a residual's near-parabola), a millionth of a
            // grid step in thickness, its value within ~p″·1e-12 (a step
            // of 1e-6 took one more evaluation on a fifth of the pixels
            // for nothing, and one of 1e-10 another).
            if (nt - t).abs() < 1e-3 {
                let v = value(p, nt);
                return if v <= ends.1 { (nt, v) } else { ends };
            }
            t = nt;
        }
    }
    // Where Newton left the interval: on a convex residual whose slope
    // keeps its sign across the interval the minimum is the end it falls
    // towards (a walk's intervals short of the minimum), which the
    // bracketed search below would reach after nine evaluations.
    if let Some(end) = convex_end(p) {
        // Horner, as the bracketed search evaluates it: the same numbers.
        let v = poly_eval(p, end).0;
        return if v <= ends.1 { (end, v) } else { ends };
    }
    poly_min_bracketed(p, ends)
}

/// The end of `[0, 1]` where `p` is lowest, if `p` is convex on the
/// interval (every Bernstein coefficient of `p″` positive: `p″` lies in
/// their convex hull) and its slope does not change sign there; `None`
/// otherwise.
fn convex_end(p: &[f64; 7]) -> Option<f64> {
    let Derivatives { d1, d2: a } = Derivatives::of(p);
    // `p″` of degree 4 in Bernstein form: b_j = Σ_{i≤j} C(j,i)/C(4,i)·a_i.
    let b = [
        a[0],
        a[0] + a[1] / 4.0,
        a[0] + a[1] / 2.0 + a[2] / 6.0,
        a[0] + 0.75 * a[1] + 0.5 * a[2] + 0.25 * a[3],
        a[0] + a[1] + a[2] + a[3] + a[4],
    ];
    if !b.iter().all(|&v| v > 0.0) {
        return None;
    }
    let slope_1: f64 = d1.iter().sum();
    if slope_1 <= 0.0 {
        Some(1.0)
    } else if p[1] >= 0.0 {
        Some(0.0)
    } else {
        None
    }
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

#[cfg(test)]
mod tests {
    use super::*;

    /// Where the minimum is an end of a convex residual, the shortcut gives
    /// what the bracketed search gives, to the bit: parabolas with their
    /// vertex beyond either end plus smaller higher powers.
    #[test]
    fn a_convex_residuals_end_is_the_bracketed_searchs() {
        let mut shortcuts = 0;
        for i in 0..400 {
            let c = |k: usize| ((i * 7 + k * 13) as f64 * 0.37).sin();
            let vertex = if i % 2 == 0 {
                1.2 + c(0).abs()
            } else {
                -0.2 - c(0).abs()
            };
            let curv = 0.1 + 5.0 * c(1).abs();
            let mut p = [0.0; 7];
            p[0] = 1.0 + curv * vertex * vertex;
            p[1] = -2.0 * curv * vertex;
            p[2] = curv;
            for (k, q) in p.iter_mut().enumerate().skip(3) {
                *q = 0.05 * curv * c(k);
            }
            let ends = if p.iter().sum::<f64>() < p[0] {
                (1.0, p.iter().sum::<f64>())
            } else {
                (0.0, p[0])
            };
            if let Some(end) = convex_end(&p) {
                shortcuts += 1;
                let v = poly_eval(&p, end).0;
                let short = if v <= ends.1 { (end, v) } else { ends };
                let full = poly_min_bracketed(&p, ends);
                assert_eq!(
                    (short.0.to_bits(), short.1.to_bits()),
                    (full.0.to_bits(), full.1.to_bits()),
                    "{p:?}"
                );
                assert_eq!(end, if vertex > 1.0 { 1.0 } else { 0.0 }, "{p:?}");
            }
        }
        // These shapes are convex with the vertex outside: every one.
        assert_eq!(shortcuts, 400);
    }

    #[test]
    fn estrins_values_and_slopes_match_horners() {
        // Irregular coefficients of the residual's size and sign pattern,
        // at points across the interval and a little beyond.
        for i in 0..50 {
            let c =
                |k: usize| ((i * 7 + k * 13) as f64 * 0.37).sin() * 10f64.powi(k as i32 % 3 - 1);
            let p = [c(0).abs(), c(1), c(2).abs(), c(3), c(4), c(5), c(6)];
            let s = Derivatives::of(&p);
            for j in 0..=12 {
                let t = -0.1 + 1.2 * j as f64 / 12.0;
                let (v, d1, d2) = poly_eval(&p, t);
                let (e1, e2) = s.at(t);
                let scale = p.iter().map(|c| c.abs()).sum::<f64>() * 30.0;
                for (a, b) in [(value(&p, t), v), (e1, d1), (e2, d2)] {
                    assert!((a - b).abs() <= 1e-14 * scale, "{p:?} at {t}: {a} vs {b}");
                }
            }
        }
    }
}
