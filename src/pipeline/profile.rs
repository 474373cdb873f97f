//! `--profile`: a small tracing layer that records every span's lifetime
//! into a fixed log-scale histogram per span name, and prints latency
//! percentiles and throughput per stage at exit.
//!
//! Spans the pipeline opens: `capture.frame` (includes waiting for the
//! camera), `ingest.frame` (calibrate + track one band), `solve.sweep`
//! (film index where needed + every row), `solve.index`, `write.sweep`
//! (the sink: EXR + summary). With no subscriber installed (neither
//! `--profile` nor `--trace`), a disabled span costs about a nanosecond.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Instant;
use tracing::span::{Attributes, Id};
use tracing::Subscriber;
use tracing_subscriber::layer::Context;
use tracing_subscriber::registry::LookupSpan;
use tracing_subscriber::Layer;

/// Sub-buckets per octave.
const SUB: u32 = 4;
/// Buckets: 2^(i/4) ns up to ~2^40 ns (18 min).
const BUCKETS: usize = 40 * SUB as usize;

/// A fixed log-scale histogram of durations.
#[derive(Clone, Debug)]
pub struct Histogram {
    buckets: [u64; BUCKETS],
    count: u64,
    sum_ns: u128,
    max_ns: u64,
}

impl Default for Histogram {
    fn default() -> Self {
        Histogram {
            buckets: [0; BUCKETS],
            count: 0,
            sum_ns: 0,
            max_ns: 0,
        }
    }
}

impl Histogram {
    /// Record one duration.
    pub fn record(&mut self, ns: u64) {
        let b = if ns <= 1 {
            0
        } else {
            let l = 63 - ns.leading_zeros();
            // Position within the octave from the next two bits.
            let frac = if l >= 2 {
                ((ns >> (l - 2)) & 3) as u32
            } else {
                0
            };
            (l * SUB + frac) as usize
        };
        self.buckets[b.min(BUCKETS - 1)] += 1;
        self.count += 1;
        self.sum_ns += u128::from(ns);
        self.max_ns = self.max_ns.max(ns);
    }

    /// The `q` quantile (0 … 1), ns, at bucket resolution (±19%).
    pub fn quantile(&self, q: f64) -> u64 {
        let target = ((self.count as f64) * q).ceil().max(1.0) as u64;
        let mut acc = 0;
        for (i, &c) in self.buckets.iter().enumerate() {
            acc += c;
            if acc >= target {
                let (l, frac) = (i as u32 / SUB, i as u32 % SUB);
                let lo = (1u64 << l) as f64 * (1.0 + f64::from(frac) / 4.0);
                return (lo * 1.125) as u64;
            }
        }
        self.max_ns
    }

    /// Samples recorded.
    pub fn count(&self) -> u64 {
        self.count
    }
}

#[derive(Default)]
struct Stats {
    by_name: BTreeMap<&'static str, Histogram>,
}

struct Start(Instant);

/// The layer. Clone it to keep a handle for [`ProfileLayer::report`].
#[derive(Clone)]
pub struct ProfileLayer {
    stats: Arc<Mutex<Stats>>,
    started: Instant,
}

impl Default for ProfileLayer {
    fn default() -> Self {
        ProfileLayer::new()
    }
}

impl ProfileLayer {
    /// A new, empty profile.
    pub fn new() -> Self {
        ProfileLayer {
            stats: Arc::default(),
            started: Instant::now(),
        }
    }

    /// The histogram of one span name.
    pub fn histogram(&self, name: &str) -> Option<Histogram> {
        let s = self.stats.lock().unwrap_or_else(|p| p.into_inner());
        s.by_name.get(name).cloned()
    }

    /// A table: per span name, count, p50/p90/p99/max and throughput.
    pub fn report(&self) -> String {
        let s = self.stats.lock().unwrap_or_else(|p| p.into_inner());
        let wall = self.started.elapsed().as_secs_f64().max(1e-9);
        let mut out = format!(
            "{:<16} {:>8} {:>10} {:>10} {:>10} {:>10} {:>10} {:>9}\n",
            "stage", "count", "mean ms", "p50 ms", "p90 ms", "p99 ms", "max ms", "per s"
        );
        for (name, h) in &s.by_name {
            let ms = |ns: u64| ns as f64 / 1e6;
            out += &format!(
                "{:<16} {:>8} {:>10.3} {:>10.3} {:>10.3} {:>10.3} {:>10.3} {:>9.1}\n",
                name,
                h.count,
                h.sum_ns as f64 / h.count.max(1) as f64 / 1e6,
                ms(h.quantile(0.5)),
                ms(h.quantile(0.9)),
                ms(h.quantile(0.99)),
                ms(h.max_ns),
                h.count as f64 / wall
            );
        }
        out
    }
}

impl<S> Layer<S> for ProfileLayer
where
    S: Subscriber + for<'a> LookupSpan<'a>,
{
    fn on_new_span(&self, _attrs: &Attributes<'_>, id: &Id, ctx: Context<'_, S>) {
        if let Some(span) = ctx.span(id) {
            span.extensions_mut().insert(Start(Instant::now()));
        }
    }

    fn on_close(&self, id: Id, ctx: Context<'_, S>) {
        let Some(span) = ctx.span(&id) else { return };
        let Some(ns) = span
            .extensions()
            .get::<Start>()
            .map(|s| s.0.elapsed().as_nanos() as u64)
        else {
            return;
        };
        let mut s = self.stats.lock().unwrap_or_else(|p| p.into_inner());
        s.by_name.entry(span.name()).or_default().record(ns);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_are_within_a_bucket() {
        let mut h = Histogram::default();
        for ns in 1..=1000u64 {
            h.record(ns * 1000);
        }
        let p50 = h.quantile(0.5) as f64;
        assert!((p50 / 500_000.0 - 1.0).abs() < 0.25, "{p50}");
        let p99 = h.quantile(0.99) as f64;
        assert!((p99 / 990_000.0 - 1.0).abs() < 0.25, "{p99}");
    }
}
