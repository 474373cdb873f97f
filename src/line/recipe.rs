//! The recipe (TOML): target thickness and specification limits per lane,
//! how much web out of its window raises an alarm, the capability window.
//!
//! ```toml
//! name = "web-demo"
//! target_nm = 320.0        # every lane, unless a [[lanes]] entry says otherwise
//! lower_nm = 310.0
//! upper_nm = 330.0
//! alarm_rows = 8           # a lane out of its window for more than 8 web rows
//! capability_rows = 512    # Cp/Cpk over the last 512 rows
//! trend_rows = 256         # machine-direction trend over the last 256 rows
//! [[lanes]]                # optional, in lane order
//! target_nm = 325.0
//! lower_nm = 315.0
//! upper_nm = 335.0
//! ```
//!
//! A lane is out of its window when its row mean is outside
//! `[lower, upper]`; rows that missed bands neither extend nor end an
//! excursion. An alarm is raised once, when the excursion passes
//! `alarm_rows`, and cleared when the lane comes back.

use super::stats::LaneStats;
use super::LineError;
use serde::Deserialize;
use std::path::Path;

/// Target and limits of one lane.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct LaneSpec {
    /// Target thickness, nm.
    pub target_nm: f64,
    /// Lower specification limit, nm.
    pub lower_nm: f64,
    /// Upper specification limit, nm.
    pub upper_nm: f64,
}

/// A recipe as written.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Recipe {
    /// Name.
    #[serde(default)]
    pub name: String,
    /// Default target, nm.
    pub target_nm: f64,
    /// Default lower limit, nm.
    pub lower_nm: f64,
    /// Default upper limit, nm.
    pub upper_nm: f64,
    /// Rows out of the window before an alarm.
    pub alarm_rows: u64,
    /// Rows of the capability window.
    #[serde(default = "default_cap")]
    pub capability_rows: usize,
    /// Rows of the trend window.
    #[serde(default = "default_trend")]
    pub trend_rows: usize,
    /// Per-lane overrides, in lane order.
    #[serde(default)]
    pub lanes: Vec<LaneSpec>,
}

fn default_cap() -> usize {
    512
}
fn default_trend() -> usize {
    256
}

impl Recipe {
    /// Parse and check a recipe.
    pub fn from_toml(text: &str, origin: &str) -> Result<Recipe, LineError> {
        let r: Recipe =
            toml::from_str(text).map_err(|e| LineError::Config(format!("recipe {origin}: {e}")))?;
        let all = std::iter::once(r.default_spec()).chain(r.lanes.iter().copied());
        for (i, l) in all.enumerate() {
            let ok = [l.target_nm, l.lower_nm, l.upper_nm]
                .iter()
                .all(|v| v.is_finite())
                && l.lower_nm < l.upper_nm;
            if !ok {
                let what = if i == 0 {
                    "the defaults".to_string()
                } else {
                    format!("lane {}", i - 1)
                };
                return Err(LineError::Config(format!(
                    "recipe {origin}: {what} need finite limits with lower < upper (got {} … {})",
                    l.lower_nm, l.upper_nm
                )));
            }
        }
        Ok(r)
    }

    /// Load a recipe file.
    pub fn load(path: &Path) -> Result<Recipe, LineError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| LineError::Config(format!("reading {}: {e}", path.display())))?;
        Recipe::from_toml(&text, &path.display().to_string())
    }

    fn default_spec(&self) -> LaneSpec {
        LaneSpec {
            target_nm: self.target_nm,
            lower_nm: self.lower_nm,
            upper_nm: self.upper_nm,
        }
    }

    /// The spec of lane `i`.
    pub fn lane(&self, i: usize) -> LaneSpec {
        self.lanes
            .get(i)
            .copied()
            .unwrap_or_else(|| self.default_spec())
    }
}

/// An alarm event.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Alarm {
    /// `"raised"` or `"cleared"`.
    pub event: &'static str,
    /// Lane index.
    pub lane: usize,
    /// `"high"` or `"low"`.
    pub side: &'static str,
    /// First web row of the excursion.
    pub from_row: i64,
    /// The row at which the event happened.
    pub at_row: i64,
    /// Rows out of the window so far.
    pub rows: u64,
    /// The lane mean at the event, nm.
    pub mean_nm: f64,
    /// The lane's window.
    pub spec: LaneSpec,
}

#[derive(Clone, Copy, Debug, Default)]
struct Excursion {
    from: i64,
    rows: u64,
    high: bool,
    raised: bool,
}

/// Alarm state per lane.
#[derive(Clone, Debug)]
pub struct Alarms {
    recipe: Recipe,
    state: Vec<Option<Excursion>>,
}

impl Alarms {
    /// Alarms for `lanes` lanes.
    pub fn new(recipe: Recipe, lanes: usize) -> Alarms {
        Alarms {
            recipe,
            state: vec![None; lanes],
        }
    }

    /// The recipe.
    pub fn recipe(&self) -> &Recipe {
        &self.recipe
    }

    /// A row's lane statistics; events go to `out`.
    pub fn push(&mut self, row: i64, complete: bool, lanes: &[LaneStats], out: &mut Vec<Alarm>) {
        if !complete {
            return;
        }
        for (i, s) in lanes.iter().enumerate() {
            let spec = self.recipe.lane(i);
            let m = s.mean_nm;
            if !m.is_finite() {
                continue;
            }
            let out_high = m > spec.upper_nm;
            let out_low = m < spec.lower_nm;
            let Some(st) = self.state.get_mut(i) else {
                continue;
            };
            match (st.as_mut(), out_high || out_low) {
                (None, true) => {
                    *st = Some(Excursion {
                        from: row,
                        rows: 1,
                        high: out_high,
                        raised: false,
                    })
                }
                (Some(e), true) => {
                    e.rows += 1;
                    e.high = out_high;
                }
                (Some(e), false) => {
                    if e.raised {
                        out.push(Alarm {
                            event: "cleared",
                            lane: i,
                            side: if e.high { "high" } else { "low" },
                            from_row: e.from,
                            at_row: row,
                            rows: e.rows,
                            mean_nm: m,
                            spec,
                        });
                    }
                    *st = None;
                }
                (None, false) => {}
            }
            if let Some(e) = st.as_mut() {
                if !e.raised && e.rows > self.recipe.alarm_rows {
                    e.raised = true;
                    out.push(Alarm {
                        event: "raised",
                        lane: i,
                        side: if e.high { "high" } else { "low" },
                        from_row: e.from,
                        at_row: row,
                        rows: e.rows,
                        mean_nm: m,
                        spec,
                    });
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const R: &str = "name = \"t\"\ntarget_nm = 100.0\nlower_nm = 95.0\nupper_nm = 105.0\nalarm_rows = 3\n[[lanes]]\ntarget_nm = 200.0\nlower_nm = 190.0\nupper_nm = 210.0\n";

    fn lane(m: f64) -> LaneStats {
        LaneStats {
            mean_nm: m,
            ..Default::default()
        }
    }

    #[test]
    fn alarm_after_the_configured_length_then_cleared() {
        let r = Recipe::from_toml(R, "t").unwrap();
        assert_eq!(r.lane(0).target_nm, 200.0);
        assert_eq!(r.lane(1).target_nm, 100.0);
        let mut a = Alarms::new(r, 2);
        let mut ev = Vec::new();
        // Lane 1 high for rows 10..=13 (4 rows > 3): raised at row 13.
        for row in 0..20 {
            let m1 = if (10..14).contains(&row) {
                106.0
            } else {
                100.0
            };
            // A flagged row inside the excursion does not count.
            a.push(row, row != 12, &[lane(200.0), lane(m1)], &mut ev);
        }
        // Rows 10, 11, 13 counted (12 flagged): 3 rows, not more than 3.
        assert!(ev.is_empty(), "{ev:?}");
        for row in 20..40 {
            let m1 = if (25..30).contains(&row) { 94.0 } else { 100.0 };
            a.push(row, true, &[lane(200.0), lane(m1)], &mut ev);
        }
        assert_eq!(ev.len(), 2, "{ev:?}");
        assert_eq!((ev[0].event, ev[0].lane, ev[0].side), ("raised", 1, "low"));
        assert_eq!((ev[0].from_row, ev[0].at_row, ev[0].rows), (25, 28, 4));
        assert_eq!((ev[1].event, ev[1].at_row, ev[1].rows), ("cleared", 30, 5));
    }

    #[test]
    fn bad_recipes_are_refused_with_the_field() {
        assert!(Recipe::from_toml("target_nm = 1.0", "x").is_err());
        let e = Recipe::from_toml(
            "target_nm = 100.0\nlower_nm = 105.0\nupper_nm = 95.0\nalarm_rows = 3\n",
            "bad.toml",
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("bad.toml") && e.contains("lower < upper"), "{e}");
        assert!(Recipe::from_toml(
            "target_nm = 100.0\nlower_nm = 95.0\nupper_nm = 105.0\nalarm_rows = 3\nbogus = 1\n",
            "x"
        )
        .is_err());
    }
}
