//! Dispersion models: how a medium's complex index `n + ik` varies with
//! wavelength.
//!
//! Wavelengths are in **nm** at this interface. The dispersion formulas
//! themselves are written, as in the refractiveindex.info database and most
//! of the literature, for λ in **µm**; each variant says which unit its
//! coefficients assume and converts internally.
//!
//! Promises:
//! - every constructor validates its input (finite numbers, `k ≥ 0`, tables
//!   strictly increasing in wavelength, a sensible range) and returns an
//!   [`OpticsError`] instead of panicking;
//! - [`Dispersion::index_at`] never panics: a non-finite or non-positive
//!   wavelength, a wavelength outside the model's valid range, or a formula
//!   that yields no physical index there (`n² ≤ 0` near a pole, NaN) is an
//!   error naming the model;
//! - a model with a valid range refuses to extrapolate; a tabulated model
//!   always has one (its first and last rows).

use super::Complex64;

/// Errors of the optics layer.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum OpticsError {
    /// A wavelength outside a model's valid range.
    #[error("wavelength {wavelength_nm} nm is outside {what}'s valid range {min_nm}–{max_nm} nm")]
    OutOfRange {
        /// What was asked.
        wavelength_nm: f64,
        /// Name of the model or file.
        what: String,
        /// Lower limit.
        min_nm: f64,
        /// Upper limit.
        max_nm: f64,
    },
    /// A model that cannot be built or evaluated.
    #[error("{0}")]
    Invalid(String),
    /// A material file (or embedded material) that cannot be read or
    /// understood: names the file and the offending field.
    #[error("{file}: {field}: {message}")]
    File {
        /// File path, or `builtin:<name>` for an embedded material.
        file: String,
        /// The YAML field (e.g. `DATA[0].coefficients`), or `-` for the file as a whole.
        field: String,
        /// What is wrong.
        message: String,
    },
}

/// One term `b·λ²/(λ² − c)` of a Sellmeier sum, λ in µm.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SellmeierTerm {
    /// Oscillator strength `B` (dimensionless).
    pub b: f64,
    /// Resonance `C` in µm² (the square of the resonance wavelength).
    pub c_um2: f64,
}

/// The refractiveindex.info dispersion formulas other than Sellmeier
/// (which has its own variant), for λ in µm. See
/// <https://refractiveindex.info/database/doc/Dispersion%20formulas.pdf>.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FormulaKind {
    /// Formula 3, polynomial: `n² = C1 + C2 λ^C3 + C4 λ^C5 + …`.
    Polynomial,
    /// Formula 4, "RefractiveIndex.INFO":
    /// `n² = C1 + C2 λ^C3/(λ² − C4^C5) + C6 λ^C7/(λ² − C8^C9) + C10 λ^C11 + C12 λ^C13 + …`.
    RefractiveIndexInfo,
    /// Formula 5, Cauchy with free exponents: `n = C1 + C2 λ^C3 + C4 λ^C5 + …`.
    Cauchy,
    /// Formula 6, gases: `n − 1 = C1 + C2/(C3 − λ⁻²) + C4/(C5 − λ⁻²) + …`.
    Gases,
    /// Formula 7, Herzberger:
    /// `n = C1 + C2/(λ² − 0.028) + C3/(λ² − 0.028)² + C4 λ² + C5 λ⁴ + C6 λ⁶`.
    Herzberger,
}

impl FormulaKind {
    /// The refractiveindex.info formula number.
    pub fn number(self) -> u8 {
        match self {
            FormulaKind::Polynomial => 3,
            FormulaKind::RefractiveIndexInfo => 4,
            FormulaKind::Cauchy => 5,
            FormulaKind::Gases => 6,
            FormulaKind::Herzberger => 7,
        }
    }

    fn max_coefficients(self) -> usize {
        match self {
            FormulaKind::Polynomial | FormulaKind::Cauchy | FormulaKind::Gases => 11,
            FormulaKind::RefractiveIndexInfo => 17,
            FormulaKind::Herzberger => 6,
        }
    }
}

/// A wavelength-dependent complex refractive index `n + ik`.
#[derive(Clone, Debug, PartialEq)]
pub enum Dispersion {
    /// The same index at every wavelength, with no range limit. (Use
    /// [`Dispersion::with_range`] for a limited one: it becomes a [`Dispersion::Cauchy`]
    /// with `b = c = 0`.)
    Constant(Complex64),
    /// Cauchy: `n = a + b/λ² + c/λ⁴` with **λ in µm** (so `b` is in µm², `c`
    /// in µm⁴), and a constant extinction coefficient `k`.
    Cauchy {
        /// Constant term.
        a: f64,
        /// λ⁻² coefficient, µm².
        b: f64,
        /// λ⁻⁴ coefficient, µm⁴.
        c: f64,
        /// Extinction coefficient (≥ 0).
        k: f64,
        /// Valid range in nm, if limited.
        range_nm: Option<(f64, f64)>,
    },
    /// Sellmeier: `n² − 1 = a + Σ bᵢ λ²/(λ² − cᵢ)` with **λ in µm**, `cᵢ` in
    /// µm², and a constant `k`. Both refractiveindex.info forms map onto it:
    /// formula 1 (`Cᵢ²`, resonance wavelengths) and formula 2 (`Cᵢ` directly);
    /// see [`Dispersion::sellmeier_formula1`] and [`Dispersion::sellmeier_formula2`].
    Sellmeier {
        /// Constant term `a` (refractiveindex.info's C1).
        a: f64,
        /// The oscillator terms.
        terms: Vec<SellmeierTerm>,
        /// Extinction coefficient (≥ 0).
        k: f64,
        /// Valid range in nm, if limited.
        range_nm: Option<(f64, f64)>,
    },
    /// Another refractiveindex.info formula (3–7), real index, λ in µm.
    Formula {
        /// Which formula.
        kind: FormulaKind,
        /// Coefficients `C1, C2, …` as in the file.
        coefficients: Vec<f64>,
        /// Valid range in nm, if limited.
        range_nm: Option<(f64, f64)>,
    },
    /// A table of `n` and `k`, linearly interpolated, valid only between its
    /// first and last wavelength.
    Tabulated {
        /// Strictly increasing wavelengths, nm.
        wavelengths_nm: Vec<f64>,
        /// Real part of the index at each wavelength.
        n: Vec<f64>,
        /// Extinction coefficient at each wavelength (≥ 0).
        k: Vec<f64>,
    },
    /// The real part from one model and the extinction coefficient from
    /// another (a refractiveindex.info file with a formula for `n` and a
    /// `tabulated k`). Valid where both are.
    Combined {
        /// Model giving `n` (its `k` is ignored).
        n: Box<Dispersion>,
        /// Model giving `k` (its `n` is ignored).
        k: Box<Dispersion>,
    },
}

fn invalid(msg: impl Into<String>) -> OpticsError {
    OpticsError::Invalid(msg.into())
}

fn check_finite(what: &str, name: &str, x: f64) -> Result<(), OpticsError> {
    if x.is_finite() {
        Ok(())
    } else {
        Err(invalid(format!("{what}: {name} must be finite, got {x}")))
    }
}

fn check_k(what: &str, k: f64) -> Result<(), OpticsError> {
    check_finite(what, "k", k)?;
    if k < 0.0 {
        return Err(invalid(format!(
            "{what}: k must be ≥ 0 (absorbing convention n + ik), got {k}"
        )));
    }
    Ok(())
}

fn check_range(what: &str, range: Option<(f64, f64)>) -> Result<(), OpticsError> {
    if let Some((lo, hi)) = range {
        if !(lo.is_finite() && hi.is_finite() && lo > 0.0 && hi >= lo) {
            return Err(invalid(format!(
                "{what}: valid range must be finite, positive and increasing, got {lo}–{hi} nm"
            )));
        }
    }
    Ok(())
}

/// Linear interpolation in a table, clamped to its end rows (the caller
/// checks the range). An empty table gives NaN, which callers refuse.
fn interp_table(wl: &[f64], n: &[f64], k: &[f64], x: f64) -> Complex64 {
    let len = wl.len().min(n.len()).min(k.len());
    if len == 0 {
        return Complex64::new(f64::NAN, f64::NAN);
    }
    let wl = &wl[..len];
    let j = wl.partition_point(|&w| w < x).min(len - 1);
    if j == 0 || wl[j] == x {
        return Complex64::new(n[j], k[j]);
    }
    let i = j - 1;
    let t = (x - wl[i]) / (wl[j] - wl[i]);
    Complex64::new(n[i] + t * (n[j] - n[i]), k[i] + t * (k[j] - k[i]))
}

fn intersect(a: Option<(f64, f64)>, b: Option<(f64, f64)>) -> Option<(f64, f64)> {
    match (a, b) {
        (None, r) | (r, None) => r,
        (Some((a0, a1)), Some((b0, b1))) => Some((a0.max(b0), a1.min(b1))),
    }
}

impl Dispersion {
    /// A lossless constant index. (Not validated, to keep this infallible:
    /// a non-finite or non-positive `n` is refused by [`Dispersion::index_at`].)
    pub fn constant(n: f64) -> Self {
        Dispersion::Constant(Complex64::new(n, 0.0))
    }

    /// A constant complex index `n + ik`, validated.
    pub fn constant_nk(n: f64, k: f64) -> Result<Self, OpticsError> {
        check_finite("constant index", "n", n)?;
        if n <= 0.0 {
            return Err(invalid(format!("constant index: n must be > 0, got {n}")));
        }
        check_k("constant index", k)?;
        Ok(Dispersion::Constant(Complex64::new(n, k)))
    }

    /// Cauchy model `n = a + b/λ² + c/λ⁴`, λ in µm, constant `k`, no range limit.
    pub fn cauchy(a: f64, b: f64, c: f64, k: f64) -> Result<Self, OpticsError> {
        for (name, x) in [("a", a), ("b", b), ("c", c)] {
            check_finite("Cauchy model", name, x)?;
        }
        check_k("Cauchy model", k)?;
        Ok(Dispersion::Cauchy {
            a,
            b,
            c,
            k,
            range_nm: None,
        })
    }

    /// Sellmeier model `n² − 1 = a + Σ bᵢ λ²/(λ² − cᵢ)`, λ in µm, `cᵢ` in µm²,
    /// constant `k`, no range limit.
    pub fn sellmeier(a: f64, terms: Vec<SellmeierTerm>, k: f64) -> Result<Self, OpticsError> {
        check_finite("Sellmeier model", "constant term", a)?;
        for (i, t) in terms.iter().enumerate() {
            check_finite("Sellmeier model", &format!("B{}", i + 1), t.b)?;
            check_finite("Sellmeier model", &format!("C{}", i + 1), t.c_um2)?;
        }
        check_k("Sellmeier model", k)?;
        Ok(Dispersion::Sellmeier {
            a,
            terms,
            k,
            range_nm: None,
        })
    }

    /// refractiveindex.info "formula 1": `n² − 1 = C1 + Σ Bᵢ λ²/(λ² − Cᵢ²)`,
    /// coefficients in file order `C1, B1, C1', B2, C2', …` (λ and `Cᵢ` in µm).
    pub fn sellmeier_formula1(coefficients: &[f64]) -> Result<Self, OpticsError> {
        Self::sellmeier_from_file_coefficients(coefficients, true)
    }

    /// refractiveindex.info "formula 2": `n² − 1 = C1 + Σ Bᵢ λ²/(λ² − Cᵢ)`,
    /// coefficients in file order `C1, B1, C1', B2, C2', …` (λ in µm, `Cᵢ` in µm²).
    pub fn sellmeier_formula2(coefficients: &[f64]) -> Result<Self, OpticsError> {
        Self::sellmeier_from_file_coefficients(coefficients, false)
    }

    fn sellmeier_from_file_coefficients(c: &[f64], squared: bool) -> Result<Self, OpticsError> {
        let form = if squared { 1 } else { 2 };
        let Some((&a, rest)) = c.split_first() else {
            return Err(invalid(format!("formula {form}: no coefficients")));
        };
        if rest.len() % 2 != 0 {
            return Err(invalid(format!(
                "formula {form}: expected C1 followed by (B, C) pairs, got {} coefficients",
                c.len()
            )));
        }
        let terms = rest
            .chunks_exact(2)
            .map(|p| SellmeierTerm {
                b: p[0],
                c_um2: if squared { p[1] * p[1] } else { p[1] },
            })
            .collect();
        Self::sellmeier(a, terms, 0.0)
    }

    /// Another refractiveindex.info formula (see [`FormulaKind`]), λ in µm.
    pub fn formula(kind: FormulaKind, coefficients: Vec<f64>) -> Result<Self, OpticsError> {
        let what = format!("formula {}", kind.number());
        if coefficients.is_empty() {
            return Err(invalid(format!("{what}: no coefficients")));
        }
        if coefficients.len() > kind.max_coefficients() {
            return Err(invalid(format!(
                "{what}: at most {} coefficients, got {}",
                kind.max_coefficients(),
                coefficients.len()
            )));
        }
        for (i, &x) in coefficients.iter().enumerate() {
            check_finite(&what, &format!("C{}", i + 1), x)?;
        }
        Ok(Dispersion::Formula {
            kind,
            coefficients,
            range_nm: None,
        })
    }

    /// A table of `n` and `k` (equal lengths, at least two rows, wavelengths
    /// in nm strictly increasing, all finite, `n > 0`, `k ≥ 0`).
    pub fn tabulated(
        wavelengths_nm: Vec<f64>,
        n: Vec<f64>,
        k: Vec<f64>,
    ) -> Result<Self, OpticsError> {
        Self::tabulated_checked(wavelengths_nm, n, k, true)
    }

    /// A table with `n` only (`k = 0`).
    pub fn tabulated_n(wavelengths_nm: Vec<f64>, n: Vec<f64>) -> Result<Self, OpticsError> {
        let k = vec![0.0; n.len()];
        Self::tabulated_checked(wavelengths_nm, n, k, true)
    }

    /// A table of `k` only, for use as the `k` part of [`Dispersion::Combined`]
    /// (its `n` is stored as 0 and never used there).
    pub fn tabulated_k(wavelengths_nm: Vec<f64>, k: Vec<f64>) -> Result<Self, OpticsError> {
        let n = vec![0.0; k.len()];
        Self::tabulated_checked(wavelengths_nm, n, k, false)
    }

    fn tabulated_checked(
        wl: Vec<f64>,
        n: Vec<f64>,
        k: Vec<f64>,
        need_n: bool,
    ) -> Result<Self, OpticsError> {
        let what = "tabulated model";
        if wl.len() != n.len() || wl.len() != k.len() {
            return Err(invalid(format!(
                "{what}: {} wavelengths but {} n and {} k values",
                wl.len(),
                n.len(),
                k.len()
            )));
        }
        if wl.len() < 2 {
            return Err(invalid(format!(
                "{what}: needs at least two rows, got {}",
                wl.len()
            )));
        }
        for (i, ((&w, &ni), &ki)) in wl.iter().zip(&n).zip(&k).enumerate() {
            if !(w.is_finite() && w > 0.0) {
                return Err(invalid(format!(
                    "{what}: row {i}: wavelength must be finite and > 0, got {w}"
                )));
            }
            if !ni.is_finite() || (need_n && ni <= 0.0) {
                return Err(invalid(format!(
                    "{what}: row {i} ({w} nm): n must be finite and > 0, got {ni}"
                )));
            }
            if !(ki.is_finite() && ki >= 0.0) {
                return Err(invalid(format!(
                    "{what}: row {i} ({w} nm): k must be finite and ≥ 0, got {ki}"
                )));
            }
            if i > 0 && w <= wl[i - 1] {
                return Err(invalid(format!(
                    "{what}: wavelengths must be strictly increasing, row {i} has {w} nm after {} nm",
                    wl[i - 1]
                )));
            }
        }
        Ok(Dispersion::Tabulated {
            wavelengths_nm: wl,
            n,
            k,
        })
    }

    /// `n` from `n_model`, `k` from `k_model`, valid where both are.
    pub fn combined(n_model: Dispersion, k_model: Dispersion) -> Result<Self, OpticsError> {
        let d = Dispersion::Combined {
            n: Box::new(n_model),
            k: Box::new(k_model),
        };
        if let Some((lo, hi)) = d.range_nm() {
            if lo > hi {
                return Err(invalid(format!(
                    "combined model: the n and k models' ranges do not overlap ({lo} > {hi} nm)"
                )));
            }
        }
        Ok(d)
    }

    /// The same model limited to `[lo_nm, hi_nm]`. A range on a table or a
    /// combined model narrows it (it never widens past the data); a constant
    /// becomes an equivalent Cauchy model with a range.
    pub fn with_range(self, lo_nm: f64, hi_nm: f64) -> Result<Self, OpticsError> {
        let range = Some((lo_nm, hi_nm));
        check_range("valid range", range)?;
        let narrowed = |own: Option<(f64, f64)>| -> Result<Option<(f64, f64)>, OpticsError> {
            let r = intersect(own, range);
            match r {
                Some((a, b)) if a > b => Err(invalid(format!(
                    "valid range {lo_nm}–{hi_nm} nm does not overlap the model's {:?}",
                    own
                ))),
                _ => Ok(r),
            }
        };
        Ok(match self {
            Dispersion::Constant(n) => Dispersion::Cauchy {
                a: n.re,
                b: 0.0,
                c: 0.0,
                k: n.im,
                range_nm: range,
            },
            Dispersion::Cauchy {
                a,
                b,
                c,
                k,
                range_nm,
            } => Dispersion::Cauchy {
                a,
                b,
                c,
                k,
                range_nm: narrowed(range_nm)?,
            },
            Dispersion::Sellmeier {
                a,
                terms,
                k,
                range_nm,
            } => Dispersion::Sellmeier {
                a,
                terms,
                k,
                range_nm: narrowed(range_nm)?,
            },
            Dispersion::Formula {
                kind,
                coefficients,
                range_nm,
            } => Dispersion::Formula {
                kind,
                coefficients,
                range_nm: narrowed(range_nm)?,
            },
            Dispersion::Tabulated {
                wavelengths_nm,
                n,
                k,
            } => {
                let (Some(&first), Some(&last)) = (wavelengths_nm.first(), wavelengths_nm.last())
                else {
                    return Err(invalid("empty table"));
                };
                let (lo, hi) = (lo_nm.max(first), hi_nm.min(last));
                if lo >= hi {
                    return Err(invalid(format!(
                        "valid range {lo_nm}–{hi_nm} nm leaves less than two rows of the table's {first}–{last} nm"
                    )));
                }
                // Trim to the rows strictly inside and add interpolated end
                // rows: under linear interpolation the values are unchanged.
                let interp = |x: f64| interp_table(&wavelengths_nm, &n, &k, x);
                let (mut w2, mut n2, mut k2) = (vec![lo], Vec::new(), Vec::new());
                let at_lo = interp(lo);
                n2.push(at_lo.re);
                k2.push(at_lo.im);
                for ((&w, &ni), &ki) in wavelengths_nm.iter().zip(&n).zip(&k) {
                    if w > lo && w < hi {
                        w2.push(w);
                        n2.push(ni);
                        k2.push(ki);
                    }
                }
                let at_hi = interp(hi);
                w2.push(hi);
                n2.push(at_hi.re);
                k2.push(at_hi.im);
                Dispersion::Tabulated {
                    wavelengths_nm: w2,
                    n: n2,
                    k: k2,
                }
            }
            Dispersion::Combined { n, k } => Dispersion::Combined {
                n: Box::new(n.with_range(lo_nm, hi_nm)?),
                k,
            },
        })
    }

    /// A short description for error messages.
    pub fn describe(&self) -> String {
        match self {
            Dispersion::Constant(_) => "constant index".into(),
            Dispersion::Cauchy { .. } => "Cauchy model".into(),
            Dispersion::Sellmeier { .. } => "Sellmeier model".into(),
            Dispersion::Formula { kind, .. } => format!("formula {} model", kind.number()),
            Dispersion::Tabulated { .. } => "tabulated model".into(),
            Dispersion::Combined { n, .. } => format!("{} with tabulated k", n.describe()),
        }
    }

    /// The valid wavelength range in nm, if the model has one.
    pub fn range_nm(&self) -> Option<(f64, f64)> {
        match self {
            Dispersion::Constant(_) => None,
            Dispersion::Cauchy { range_nm, .. }
            | Dispersion::Sellmeier { range_nm, .. }
            | Dispersion::Formula { range_nm, .. } => *range_nm,
            Dispersion::Tabulated { wavelengths_nm, .. } => {
                match (wavelengths_nm.first(), wavelengths_nm.last()) {
                    (Some(&a), Some(&b)) => Some((a, b)),
                    _ => Some((f64::NAN, f64::NAN)),
                }
            }
            Dispersion::Combined { n, k } => intersect(n.range_nm(), k.range_nm()),
        }
    }

    /// The complex index at a node `wavelength_nm` of a passband centred
    /// on `center_nm`: where the node lies outside the model's range but
    /// the centre inside, the index at the range's nearest end (a
    /// passband's tail past a table's end, ~2 FWHM at most, is read at
    /// the end: the model says nothing beyond it, and refusing the band
    /// would refuse a measurement the centre's index describes).
    pub fn index_in_passband(
        &self,
        wavelength_nm: f64,
        center_nm: f64,
    ) -> Result<Complex64, OpticsError> {
        match (self.index_at(wavelength_nm), self.range_nm()) {
            (Err(e), Some((lo, hi))) if (lo..=hi).contains(&center_nm) => {
                self.index_at(wavelength_nm.clamp(lo, hi)).map_err(|_| e)
            }
            (r, _) => r,
        }
    }

    /// The complex index at `wavelength_nm`.
    pub fn index_at(&self, wavelength_nm: f64) -> Result<Complex64, OpticsError> {
        // The model's name is only needed for an error: build it then, so
        // the success path (called per pixel by renderers) never allocates.
        self.index_named(wavelength_nm, "")
            .or_else(|_| self.index_named(wavelength_nm, &self.describe()))
    }

    /// As [`Dispersion::index_at`], naming the model `what` in errors (a
    /// material name or file).
    pub fn index_named(&self, wavelength_nm: f64, what: &str) -> Result<Complex64, OpticsError> {
        if !(wavelength_nm.is_finite() && wavelength_nm > 0.0) {
            return Err(invalid(format!(
                "{what}: wavelength must be finite and > 0 nm, got {wavelength_nm}"
            )));
        }
        if let Some((lo, hi)) = self.range_nm() {
            // NaN limits (never built by the constructors) also refuse.
            if !(wavelength_nm >= lo && wavelength_nm <= hi) {
                return Err(OpticsError::OutOfRange {
                    wavelength_nm,
                    what: what.to_string(),
                    min_nm: lo,
                    max_nm: hi,
                });
            }
        }
        let idx = self.eval(wavelength_nm, what)?;
        if !(idx.re.is_finite() && idx.im.is_finite()) || idx.re <= 0.0 || idx.im < 0.0 {
            return Err(invalid(format!(
                "{what}: no physical index at {wavelength_nm} nm (n = {}, k = {})",
                idx.re, idx.im
            )));
        }
        Ok(idx)
    }

    /// Evaluate without the range check (the caller did it).
    fn eval(&self, wavelength_nm: f64, what: &str) -> Result<Complex64, OpticsError> {
        let l = wavelength_nm * 1e-3; // µm
        let l2 = l * l;
        let from_n2 = |n2: f64, k: f64| -> Result<Complex64, OpticsError> {
            if n2 > 0.0 {
                Ok(Complex64::new(n2.sqrt(), k))
            } else {
                Err(invalid(format!(
                    "{what}: n² = {n2} at {wavelength_nm} nm (at or beyond a resonance of the formula)"
                )))
            }
        };
        match self {
            Dispersion::Constant(n) => Ok(*n),
            Dispersion::Cauchy { a, b, c, k, .. } => {
                Ok(Complex64::new(a + b / l2 + c / (l2 * l2), *k))
            }
            Dispersion::Sellmeier { a, terms, k, .. } => {
                let n2 = 1.0 + a + terms.iter().map(|t| t.b * l2 / (l2 - t.c_um2)).sum::<f64>();
                from_n2(n2, *k)
            }
            Dispersion::Formula {
                kind, coefficients, ..
            } => {
                let c = |i: usize| coefficients.get(i).copied().unwrap_or(0.0);
                let pairs_from = |start: usize| {
                    (start..coefficients.len())
                        .step_by(2)
                        .map(|i| c(i) * l.powf(c(i + 1)))
                        .sum::<f64>()
                };
                match kind {
                    FormulaKind::Polynomial => from_n2(c(0) + pairs_from(1), 0.0),
                    FormulaKind::RefractiveIndexInfo => {
                        let mut n2 = c(0);
                        for i in [1usize, 5] {
                            if i < coefficients.len() {
                                n2 += c(i) * l.powf(c(i + 1)) / (l2 - c(i + 2).powf(c(i + 3)));
                            }
                        }
                        if coefficients.len() > 9 {
                            n2 += pairs_from(9);
                        }
                        from_n2(n2, 0.0)
                    }
                    FormulaKind::Cauchy => Ok(Complex64::new(c(0) + pairs_from(1), 0.0)),
                    FormulaKind::Gases => {
                        let inv = 1.0 / l2;
                        let s: f64 = (1..coefficients.len())
                            .step_by(2)
                            .map(|i| c(i) / (c(i + 1) - inv))
                            .sum();
                        Ok(Complex64::new(1.0 + c(0) + s, 0.0))
                    }
                    FormulaKind::Herzberger => {
                        let x = l2 - 0.028;
                        Ok(Complex64::new(
                            c(0) + c(1) / x
                                + c(2) / (x * x)
                                + c(3) * l2
                                + c(4) * l2 * l2
                                + c(5) * l2 * l2 * l2,
                            0.0,
                        ))
                    }
                }
            }
            Dispersion::Tabulated {
                wavelengths_nm,
                n,
                k,
            } => Ok(interp_table(wavelengths_nm, n, k, wavelength_nm)),
            Dispersion::Combined { n, k } => {
                let re = n.eval(wavelength_nm, what)?.re;
                let im = k.eval(wavelength_nm, what)?.im;
                Ok(Complex64::new(re, im))
            }
        }
    }

    /// Whether the model is valid and lossless (`k = 0`) everywhere in
    /// `[lo_nm, hi_nm]`: then the real-coefficient fast path applies there.
    /// `false` when the interval is not inside the valid range.
    pub fn is_lossless_in(&self, lo_nm: f64, hi_nm: f64) -> bool {
        if !(lo_nm.is_finite() && hi_nm.is_finite() && lo_nm > 0.0 && lo_nm <= hi_nm) {
            return false;
        }
        if let Some((a, b)) = self.range_nm() {
            if !(lo_nm >= a && hi_nm <= b) {
                return false;
            }
        }
        match self {
            Dispersion::Constant(n) => n.im == 0.0,
            Dispersion::Cauchy { k, .. } | Dispersion::Sellmeier { k, .. } => *k == 0.0,
            Dispersion::Formula { .. } => true,
            Dispersion::Tabulated {
                wavelengths_nm, k, ..
            } => {
                // Rows inside the interval plus the rows bracketing its ends
                // (interpolation is linear, so these decide).
                let lo_i = wavelengths_nm
                    .partition_point(|&w| w <= lo_nm)
                    .saturating_sub(1);
                let hi_i = wavelengths_nm.partition_point(|&w| w < hi_nm);
                k.iter()
                    .take(hi_i.saturating_add(1))
                    .skip(lo_i)
                    .all(|&ki| ki == 0.0)
            }
            Dispersion::Combined { k, .. } => k.is_lossless_in(lo_nm, hi_nm),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn constant_has_no_range_and_refuses_bad_wavelengths() {
        let d = Dispersion::constant(1.5);
        assert_eq!(d.index_at(550.0).unwrap(), Complex64::new(1.5, 0.0));
        assert_eq!(d.range_nm(), None);
        for bad in [f64::NAN, 0.0, -3.0, f64::INFINITY] {
            assert!(d.index_at(bad).is_err());
        }
        assert!(Dispersion::constant(f64::NAN).index_at(500.0).is_err());
        assert!(Dispersion::constant(-1.0).index_at(500.0).is_err());
    }

    #[test]
    fn cauchy_uses_micrometres() {
        // n = 1.5 + 0.01/λ² at λ = 0.5 µm: 1.5 + 0.04.
        let d = Dispersion::cauchy(1.5, 0.01, 0.0, 0.0).unwrap();
        assert!((d.index_at(500.0).unwrap().re - 1.54).abs() < 1e-15);
        let d = Dispersion::cauchy(1.5, 0.0, 0.001, 0.0).unwrap();
        assert!((d.index_at(500.0).unwrap().re - 1.516).abs() < 1e-14);
        assert!(Dispersion::cauchy(f64::NAN, 0.0, 0.0, 0.0).is_err());
        assert!(Dispersion::cauchy(1.5, 0.0, 0.0, -0.1).is_err());
    }

    #[test]
    fn ranges_refuse_outside_and_name_the_model() {
        let d = Dispersion::cauchy(1.5, 0.0, 0.0, 0.0)
            .unwrap()
            .with_range(400.0, 700.0)
            .unwrap();
        assert!(d.index_at(400.0).is_ok() && d.index_at(700.0).is_ok());
        match d.index_named(399.0, "my-film") {
            Err(OpticsError::OutOfRange {
                what,
                min_nm,
                max_nm,
                ..
            }) => {
                assert_eq!((what.as_str(), min_nm, max_nm), ("my-film", 400.0, 700.0));
            }
            other => panic!("{other:?}"),
        }
        let c = Dispersion::constant(1.4).with_range(400.0, 700.0).unwrap();
        assert_eq!(c.index_at(500.0).unwrap(), Complex64::new(1.4, 0.0));
        assert!(c.index_at(300.0).is_err());
        assert!(Dispersion::constant(1.4).with_range(700.0, 400.0).is_err());
    }

    #[test]
    fn sellmeier_forms_agree_and_a_pole_is_an_error() {
        // The same oscillator written both ways.
        let f1 = Dispersion::sellmeier_formula1(&[0.0, 0.6961663, 0.0684043]).unwrap();
        let f2 = Dispersion::sellmeier_formula2(&[0.0, 0.6961663, 0.0684043f64.powi(2)]).unwrap();
        let (a, b) = (f1.index_at(633.0).unwrap(), f2.index_at(633.0).unwrap());
        assert!((a - b).norm() < 1e-15);
        // Exactly at the resonance λ = 68.4 nm there is no index.
        assert!(f1.index_at(68.4043).is_err());
        assert!(Dispersion::sellmeier_formula1(&[0.0, 1.0]).is_err());
        assert!(Dispersion::sellmeier_formula1(&[]).is_err());
    }

    #[test]
    fn tabulated_interpolates_linearly_and_checks_order() {
        let d = Dispersion::tabulated(
            vec![400.0, 500.0, 600.0],
            vec![1.5, 1.4, 1.3],
            vec![0.0, 0.1, 0.0],
        )
        .unwrap();
        let i = d.index_at(450.0).unwrap();
        assert!((i.re - 1.45).abs() < 1e-15 && (i.im - 0.05).abs() < 1e-15);
        assert_eq!(d.index_at(600.0).unwrap(), Complex64::new(1.3, 0.0));
        assert_eq!(d.index_at(400.0).unwrap(), Complex64::new(1.5, 0.0));
        assert!(matches!(
            d.index_at(601.0),
            Err(OpticsError::OutOfRange { .. })
        ));
        assert!(!d.is_lossless_in(400.0, 600.0));
        assert!(!d.is_lossless_in(405.0, 420.0)); // bracketed by k = 0.1 at 500
        assert!(Dispersion::tabulated(vec![400.0, 400.0], vec![1.0, 1.0], vec![0.0, 0.0]).is_err());
        assert!(Dispersion::tabulated(vec![400.0, 500.0], vec![1.0], vec![0.0, 0.0]).is_err());
        assert!(
            Dispersion::tabulated(vec![400.0, 500.0], vec![1.0, f64::NAN], vec![0.0, 0.0]).is_err()
        );
        assert!(Dispersion::tabulated(vec![400.0], vec![1.0], vec![0.0]).is_err());
        let lossless =
            Dispersion::tabulated_n(vec![400.0, 500.0, 600.0], vec![1.5, 1.4, 1.3]).unwrap();
        assert!(lossless.is_lossless_in(400.0, 600.0));
        assert!(!lossless.is_lossless_in(300.0, 600.0));
    }

    #[test]
    fn table_with_range_narrows() {
        let d = Dispersion::tabulated_n(vec![400.0, 500.0, 600.0], vec![1.5, 1.4, 1.3])
            .unwrap()
            .with_range(450.0, 550.0)
            .unwrap();
        assert_eq!(d.range_nm(), Some((450.0, 550.0)));
        assert!((d.index_at(450.0).unwrap().re - 1.45).abs() < 1e-15);
        assert!(d.index_at(420.0).is_err());
    }

    #[test]
    fn formula_4_matches_devore_closed_form() {
        // Devore (1951), rutile ordinary ray: n² = 5.913 + 0.2441/(λ² − 0.0803).
        let d = Dispersion::formula(
            FormulaKind::RefractiveIndexInfo,
            vec![5.913, 0.2441, 0.0, 0.0803, 1.0, 0.0, 0.0, 0.0, 1.0],
        )
        .unwrap();
        let l: f64 = 0.5893;
        let want = (5.913 + 0.2441 / (l * l - 0.0803)).sqrt();
        assert!((d.index_at(589.3).unwrap().re - want).abs() < 1e-14);
    }

    #[test]
    fn combined_takes_n_and_k_from_each() {
        let n = Dispersion::cauchy(1.5, 0.0, 0.0, 0.0)
            .unwrap()
            .with_range(300.0, 900.0)
            .unwrap();
        let k = Dispersion::tabulated_k(vec![400.0, 800.0], vec![0.0, 0.4]).unwrap();
        let d = Dispersion::combined(n, k).unwrap();
        assert_eq!(d.range_nm(), Some((400.0, 800.0)));
        let i = d.index_at(600.0).unwrap();
        assert!((i.re - 1.5).abs() < 1e-15 && (i.im - 0.2).abs() < 1e-15);
        assert!(d.index_at(350.0).is_err());
    }
    #[test]
    fn a_passbands_tail_past_a_table_reads_the_tables_end() {
        let d = Dispersion::tabulated_n(vec![400.0, 500.0, 700.0], vec![1.50, 1.48, 1.46]).unwrap();
        // Inside: the table.
        assert_eq!(
            d.index_in_passband(450.0, 405.0).unwrap(),
            d.index_at(450.0).unwrap()
        );
        // A node below the table, its band's centre inside: the end.
        assert!(d.index_at(381.0).is_err());
        assert_eq!(d.index_in_passband(381.0, 402.0).unwrap().re, 1.50);
        assert_eq!(d.index_in_passband(720.0, 695.0).unwrap().re, 1.46);
        // A band centred outside stays an error.
        assert!(d.index_in_passband(381.0, 390.0).is_err());
    }
}
