//! Settling model of the liquid-crystal filter.
//!
//! Promise: a first-order approach of the passband centre to its target. The
//! time to reach 95 % of a step (`t95`) is independent of the step size (as
//! on real liquid-crystal filters), grows when the liquid crystal is cold, and
//! carries up to [`SettleParams::jitter_max_us`] of deterministic jitter from
//! a seeded PRNG. Pure: every call takes the time as an argument.

/// ln(20): a first-order system reaches 95 % of a step after ln(20) time
/// constants.
const LN_20: f64 = 2.995_732_273_553_991;

/// Reference temperature at which `t95_us` holds, in centi-°C.
pub const REFERENCE_TEMP_CENTI_C: i32 = 2500;

/// Parameters of the settling model.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SettleParams {
    /// Time to 95 % of a step at the reference temperature, in µs.
    pub t95_us: u32,
    /// Largest extra settle time added by jitter, in µs.
    pub jitter_max_us: u32,
}

impl SettleParams {
    /// Visible-range unit: 95 % in 50 ms, 2 ms jitter.
    pub const VISIBLE: Self = Self {
        t95_us: 50_000,
        jitter_max_us: 2_000,
    };
    /// Near-infrared unit: 95 % in 150 ms, 2 ms jitter.
    pub const NIR: Self = Self {
        t95_us: 150_000,
        jitter_max_us: 2_000,
    };
}

/// How much slower the liquid crystal is at `temp_centi_c` than at 25 °C.
///
/// irid's choice: the viscosity of nematic LC roughly doubles per 10 °C of
/// cooling in the working range, so the factor is 2^((25 − T)/10), clamped to
/// [0.5, 8] to stay sane outside it.
pub fn cold_factor(temp_centi_c: i32) -> f64 {
    let t = f64::from(temp_centi_c) / 100.0;
    let f = libm::exp2((25.0 - t) / 10.0);
    f.clamp(0.5, 8.0)
}

/// Small deterministic PRNG (xorshift64*), so jitter is reproducible from a seed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Prng(u64);

impl Prng {
    /// Seeded generator; a zero seed is remapped (xorshift would stick at 0).
    pub const fn new(seed: u64) -> Self {
        Self(if seed == 0 {
            0x9E37_79B9_7F4A_7C15
        } else {
            seed
        })
    }

    /// Next pseudo-random value.
    pub fn next_u64(&mut self) -> u64 {
        let mut x = self.0;
        x ^= x >> 12;
        x ^= x << 25;
        x ^= x >> 27;
        self.0 = x;
        x.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    /// Uniform in `0..=max`.
    pub fn below_inclusive(&mut self, max: u32) -> u32 {
        (self.next_u64() % (u64::from(max) + 1)) as u32
    }
}

/// One transition of the passband centre.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Motion {
    from_centi: f64,
    target_centi: u32,
    start_us: u64,
    /// Time constant in µs (never below 1).
    tau_us: f64,
    settle_us: u64,
}

impl Motion {
    /// A filter resting at `centi_nm`.
    pub fn resting(centi_nm: u32) -> Self {
        Self {
            from_centi: f64::from(centi_nm),
            target_centi: centi_nm,
            start_us: 0,
            tau_us: 1.0,
            settle_us: 0,
        }
    }

    /// Start moving from wherever the passband is at `now_us` towards
    /// `target`. Returns the new motion; it is settled (95 %) at
    /// [`Motion::settled_at`].
    pub fn retarget(
        &self,
        target: u32,
        now_us: u64,
        params: &SettleParams,
        temp_centi_c: i32,
        rng: &mut Prng,
    ) -> Self {
        let from = self.position_centi(now_us);
        let t95 = f64::from(params.t95_us) * cold_factor(temp_centi_c);
        let jitter = rng.below_inclusive(params.jitter_max_us);
        // Float → int casts saturate, so an absurd t95 cannot overflow.
        let settle_us = (t95 as u64).saturating_add(u64::from(jitter));
        Self {
            from_centi: from,
            target_centi: target,
            start_us: now_us,
            tau_us: (t95 / LN_20).max(1.0),
            settle_us,
        }
    }

    /// Passband centre at `now_us`, in centi-nm.
    pub fn position_centi(&self, now_us: u64) -> f64 {
        let t = now_us.saturating_sub(self.start_us) as f64;
        let target = f64::from(self.target_centi);
        target + (self.from_centi - target) * libm::exp(-t / self.tau_us)
    }

    /// Target of this motion, in centi-nm.
    pub fn target(&self) -> u32 {
        self.target_centi
    }

    /// When the motion counts as settled (95 % plus jitter).
    pub fn settled_at(&self) -> u64 {
        self.start_us.saturating_add(self.settle_us)
    }

    /// Whether the motion has settled at `now_us`.
    pub fn is_settled(&self, now_us: u64) -> bool {
        now_us >= self.settled_at()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reaches_95_percent_at_t95() {
        let mut rng = Prng::new(1);
        let p = SettleParams {
            t95_us: 50_000,
            jitter_max_us: 0,
        };
        let m =
            Motion::resting(40_000).retarget(70_000, 1_000, &p, REFERENCE_TEMP_CENTI_C, &mut rng);
        let at = m.position_centi(1_000 + 50_000);
        let frac = (at - 40_000.0) / 30_000.0;
        assert!((frac - 0.95).abs() < 0.001, "{frac}");
        assert_eq!(m.settled_at(), 51_000);
        assert!(!m.is_settled(50_999));
        assert!(m.is_settled(51_000));
    }

    #[test]
    fn cold_is_slower_and_jitter_is_bounded_and_reproducible() {
        let p = SettleParams::VISIBLE;
        let mut a = Prng::new(7);
        let mut b = Prng::new(7);
        for _ in 0..100 {
            let warm = Motion::resting(40_000).retarget(50_000, 0, &p, 2500, &mut a);
            let same = Motion::resting(40_000).retarget(50_000, 0, &p, 2500, &mut b);
            assert_eq!(warm.settled_at(), same.settled_at());
            assert!((50_000..=52_000).contains(&warm.settled_at()));
        }
        let cold = Motion::resting(40_000).retarget(50_000, 0, &p, 500, &mut a);
        assert!(cold.settled_at() >= 200_000, "{}", cold.settled_at());
    }

    #[test]
    fn retarget_midway_starts_from_current_position() {
        let p = SettleParams::VISIBLE;
        let mut rng = Prng::new(3);
        let m = Motion::resting(40_000).retarget(60_000, 0, &p, 2500, &mut rng);
        let mid = m.position_centi(10_000);
        let n = m.retarget(40_000, 10_000, &p, 2500, &mut rng);
        assert!((n.position_centi(10_000) - mid).abs() < 1e-6);
    }
}
