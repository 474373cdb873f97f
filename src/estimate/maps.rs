//! Parameter maps: the result of fitting a cube, one value per pixel per
//! channel, with a validity flag and a reason code.
//!
//! Invalid pixels hold NaN in every estimate channel and a non-zero
//! [`Reason`]. A valid pixel may still carry a warning reason (for example
//! [`Reason::AngleNotIdentifiable`]), so `valid` and `reason` are separate.

/// Why a pixel is invalid, or what to be careful about on a valid one.
/// The numeric codes are the file format (the EXR `reason` channel).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum Reason {
    /// Valid, nothing to report.
    Ok = 0,
    /// A band value is NaN or infinite.
    NonFinite = 1,
    /// Too dark to measure (below the calibration's floor).
    Dark = 2,
    /// A band is saturated.
    Saturated = 3,
    /// Bands are missing (not captured in this sweep).
    MissingBands = 4,
    /// No fringe in the band range and the level alone cannot fix the thickness.
    NoFringe = 5,
    /// Two fringe orders fit the spectrum about equally well.
    AmbiguousOrder = 6,
    /// The best model leaves residuals well above the noise.
    PoorFit = 7,
    /// Valid thickness, but the angle is not identifiable from the data
    /// (small angles, Brewster's angle for p): σ_θ says how little is known.
    AngleNotIdentifiable = 8,
    /// Reflectance outside what the model can produce (e.g. above 1 or below 0).
    OutOfModel = 9,
    /// The pixel lies outside the region the caller asked to solve.
    Masked = 10,
    /// The film's fringes are beyond what the bands resolve (too thick for
    /// the band spacing or the passband width): no trustworthy thickness.
    Unresolved = 11,
    /// The estimate is pinned at a bound of its search (thickness, angle or
    /// the film index): the truth may lie beyond it.
    AtBound = 12,
}

impl Reason {
    /// Whether a pixel with this reason still carries a valid estimate.
    pub fn is_valid(self) -> bool {
        matches!(self, Reason::Ok | Reason::AngleNotIdentifiable)
    }

    /// A short name for summaries and documentation.
    pub fn name(self) -> &'static str {
        match self {
            Reason::Ok => "ok",
            Reason::NonFinite => "non-finite input",
            Reason::Dark => "dark",
            Reason::Saturated => "saturated",
            Reason::MissingBands => "missing bands",
            Reason::NoFringe => "no fringe in range",
            Reason::AmbiguousOrder => "ambiguous order",
            Reason::PoorFit => "poor fit",
            Reason::AngleNotIdentifiable => "angle not identifiable",
            Reason::OutOfModel => "out of model",
            Reason::Masked => "masked",
            Reason::Unresolved => "fringes unresolved",
            Reason::AtBound => "at search bound",
        }
    }

    /// Every reason, in code order.
    pub const ALL: [Reason; 13] = [
        Reason::Ok,
        Reason::NonFinite,
        Reason::Dark,
        Reason::Saturated,
        Reason::MissingBands,
        Reason::NoFringe,
        Reason::AmbiguousOrder,
        Reason::PoorFit,
        Reason::AngleNotIdentifiable,
        Reason::OutOfModel,
        Reason::Masked,
        Reason::Unresolved,
        Reason::AtBound,
    ];

    /// The reason with this code.
    pub fn from_code(code: u8) -> Option<Reason> {
        Reason::ALL.get(usize::from(code)).copied()
    }
}

/// One pixel's estimate. Angles in degrees, lengths in nm.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PixelEstimate {
    /// Film thickness.
    pub thickness_nm: f64,
    /// Film index used (the global estimate or the known value), at the
    /// middle band for a dispersive film.
    pub n_film: f64,
    /// Incidence angle (estimated or known).
    pub theta_deg: f64,
    /// Standard error of the thickness, including the global index's share.
    pub sigma_thickness_nm: f64,
    /// Standard error of the angle (0 when the angle was known).
    pub sigma_theta_deg: f64,
    /// RMS of the reflectance residuals of the final model.
    pub residual_rms: f64,
    /// Why the pixel is invalid, or a warning.
    pub reason: Reason,
}

impl PixelEstimate {
    /// An invalid pixel: NaN estimates and the reason.
    pub fn invalid(reason: Reason) -> Self {
        PixelEstimate {
            thickness_nm: f64::NAN,
            n_film: f64::NAN,
            theta_deg: f64::NAN,
            sigma_thickness_nm: f64::NAN,
            sigma_theta_deg: f64::NAN,
            residual_rms: f64::NAN,
            reason,
        }
    }

    /// Whether the estimate is valid.
    pub fn is_valid(&self) -> bool {
        self.reason.is_valid()
    }
}

/// The keys of [`MapMeta::quality`], in the order they are written.
pub const QUALITY_KEYS: [&str; 8] = [
    "noise_sigma",
    "noise_source",
    "level",
    "level_gain",
    "level_offset",
    "thickness_range_nm",
    "optical_thickness_max_nm",
    "fit_test",
];

/// Keys of [`MapMeta::quality`] written only where they have something
/// to say (after [`QUALITY_KEYS`]).
pub const QUALITY_OPTIONAL_KEYS: [&str; 2] = ["level_note", "band_shift"];

/// Metadata written beside the maps.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MapMeta {
    /// Solver mode name.
    pub mode: String,
    /// Band centres, nm, in cube plane order.
    pub wavelengths_nm: Vec<f64>,
    /// Band FWHMs, nm.
    pub fwhm_nm: Vec<f64>,
    /// Global film index (estimated or known).
    pub n_film: f64,
    /// Its standard error (0 when known).
    pub n_film_sigma: f64,
    /// Whether the film index was estimated.
    pub n_film_estimated: bool,
    /// A note on the index estimate (e.g. an unresolved twin).
    pub n_film_note: String,
    /// Polarisation name.
    pub polarization: String,
    /// What the fit was judged against: noise model, level, thickness range
    /// (key, value), written as `irid.<key>` attributes.
    pub quality: Vec<(String, String)>,
}

/// Per-pixel parameter maps, row-major `width × height`.
#[derive(Clone, Debug, PartialEq)]
pub struct ParamMaps {
    /// Width.
    pub width: usize,
    /// Height.
    pub height: usize,
    /// Film thickness, nm.
    pub thickness_nm: Vec<f32>,
    /// Film index.
    pub n_film: Vec<f32>,
    /// Incidence angle, degrees.
    pub theta_deg: Vec<f32>,
    /// σ of the thickness, nm.
    pub sigma_thickness_nm: Vec<f32>,
    /// σ of the angle, degrees.
    pub sigma_theta_deg: Vec<f32>,
    /// Residual RMS.
    pub residual_rms: Vec<f32>,
    /// 1 valid, 0 invalid.
    pub valid: Vec<f32>,
    /// [`Reason`] code.
    pub reason: Vec<f32>,
    /// Metadata.
    pub meta: MapMeta,
}

/// One row of [`ParamMaps`], writable on its own.
#[derive(Debug)]
pub struct MapRowMut<'a> {
    thickness_nm: &'a mut [f32],
    n_film: &'a mut [f32],
    theta_deg: &'a mut [f32],
    sigma_thickness_nm: &'a mut [f32],
    sigma_theta_deg: &'a mut [f32],
    residual_rms: &'a mut [f32],
    valid: &'a mut [f32],
    reason: &'a mut [f32],
}

impl MapRowMut<'_> {
    /// Store pixel `x`'s estimate (invalid pixels: NaN estimates, their
    /// reason code).
    pub fn set(&mut self, x: usize, e: &PixelEstimate) {
        if x >= self.valid.len() {
            return;
        }
        let valid = e.is_valid();
        let v = |x: f64| if valid { x as f32 } else { f32::NAN };
        self.thickness_nm[x] = v(e.thickness_nm);
        self.n_film[x] = v(e.n_film);
        self.theta_deg[x] = v(e.theta_deg);
        self.sigma_thickness_nm[x] = v(e.sigma_thickness_nm);
        self.sigma_theta_deg[x] = v(e.sigma_theta_deg);
        self.residual_rms[x] = v(e.residual_rms);
        self.valid[x] = if valid { 1.0 } else { 0.0 };
        self.reason[x] = f32::from(e.reason as u8);
    }

    /// Store a whole row of estimates.
    pub fn set_all(&mut self, est: &[PixelEstimate]) {
        for (x, e) in est.iter().enumerate() {
            self.set(x, e);
        }
    }
}

impl ParamMaps {
    /// Maps of the given size, every pixel invalid ([`Reason::Masked`]).
    pub fn new(width: usize, height: usize) -> Self {
        let n = width * height;
        let nan = vec![f32::NAN; n];
        ParamMaps {
            width,
            height,
            thickness_nm: nan.clone(),
            n_film: nan.clone(),
            theta_deg: nan.clone(),
            sigma_thickness_nm: nan.clone(),
            sigma_theta_deg: nan.clone(),
            residual_rms: nan,
            valid: vec![0.0; n],
            reason: vec![f32::from(Reason::Masked as u8); n],
            meta: MapMeta::default(),
        }
    }

    /// Maps of the given size whose every pixel the caller is about to
    /// write: zeroed, which for large maps means fresh pages from the OS
    /// that the writing threads fault in, in parallel (no serial fill).
    /// Not a valid state to publish as is.
    pub(crate) fn for_overwrite(width: usize, height: usize) -> Self {
        let n = width * height;
        ParamMaps {
            width,
            height,
            thickness_nm: vec![0.0; n],
            n_film: vec![0.0; n],
            theta_deg: vec![0.0; n],
            sigma_thickness_nm: vec![0.0; n],
            sigma_theta_deg: vec![0.0; n],
            residual_rms: vec![0.0; n],
            valid: vec![0.0; n],
            reason: vec![0.0; n],
            meta: MapMeta::default(),
        }
    }

    /// Store pixel (x, y)'s estimate.
    pub fn set(&mut self, x: usize, y: usize, e: &PixelEstimate) {
        let i = y * self.width + x;
        self.set_index(i, e);
    }

    /// Store the estimate of the pixel with row-major index `i`.
    pub fn set_index(&mut self, i: usize, e: &PixelEstimate) {
        if i >= self.valid.len() {
            return;
        }
        let r = i..i + 1;
        MapRowMut {
            thickness_nm: &mut self.thickness_nm[r.clone()],
            n_film: &mut self.n_film[r.clone()],
            theta_deg: &mut self.theta_deg[r.clone()],
            sigma_thickness_nm: &mut self.sigma_thickness_nm[r.clone()],
            sigma_theta_deg: &mut self.sigma_theta_deg[r.clone()],
            residual_rms: &mut self.residual_rms[r.clone()],
            valid: &mut self.valid[r.clone()],
            reason: &mut self.reason[r],
        }
        .set(0, e);
    }

    /// Rows `rows` as independent mutable views, one per row, so that
    /// rows can be written in parallel (the vector is per block of rows,
    /// not per pixel).
    pub fn rows_mut(&mut self, rows: std::ops::Range<usize>) -> Vec<MapRowMut<'_>> {
        let w = self.width;
        let (a, b) = (
            rows.start.min(self.height) * w,
            rows.end.min(self.height) * w,
        );
        let mut out = Vec::with_capacity(rows.len());
        if w == 0 || a >= b {
            return out;
        }
        let mut ch = [
            &mut self.thickness_nm[a..b],
            &mut self.n_film[a..b],
            &mut self.theta_deg[a..b],
            &mut self.sigma_thickness_nm[a..b],
            &mut self.sigma_theta_deg[a..b],
            &mut self.residual_rms[a..b],
            &mut self.valid[a..b],
            &mut self.reason[a..b],
        ]
        .map(|c| c.chunks_mut(w));
        while let [Some(t), Some(n), Some(th), Some(st), Some(sth), Some(r), Some(v), Some(re)] =
            ch.each_mut().map(Iterator::next)
        {
            out.push(MapRowMut {
                thickness_nm: t,
                n_film: n,
                theta_deg: th,
                sigma_thickness_nm: st,
                sigma_theta_deg: sth,
                residual_rms: r,
                valid: v,
                reason: re,
            });
        }
        out
    }

    /// Pixel (x, y)'s estimate read back.
    pub fn get(&self, x: usize, y: usize) -> PixelEstimate {
        let i = y * self.width + x;
        PixelEstimate {
            thickness_nm: f64::from(self.thickness_nm[i]),
            n_film: f64::from(self.n_film[i]),
            theta_deg: f64::from(self.theta_deg[i]),
            sigma_thickness_nm: f64::from(self.sigma_thickness_nm[i]),
            sigma_theta_deg: f64::from(self.sigma_theta_deg[i]),
            residual_rms: f64::from(self.residual_rms[i]),
            reason: Reason::from_code(self.reason[i] as u8).unwrap_or(Reason::OutOfModel),
        }
    }

    /// Number of valid pixels.
    pub fn valid_count(&self) -> usize {
        self.valid.iter().filter(|v| **v > 0.5).count()
    }

    /// The channels by file name, in a fixed order.
    pub fn channels(&self) -> [(&'static str, &[f32]); 8] {
        [
            ("thickness_nm", &self.thickness_nm),
            ("n_film", &self.n_film),
            ("theta_deg", &self.theta_deg),
            ("sigma_thickness_nm", &self.sigma_thickness_nm),
            ("sigma_theta_deg", &self.sigma_theta_deg),
            ("residual_rms", &self.residual_rms),
            ("valid", &self.valid),
            ("reason", &self.reason),
        ]
    }
}
