//! Helpers shared by the estimation tests: the truth's angle as a known
//! per-pixel map.

use irid::scene::{AngleKnowledge, Scene};

/// `s` with its synthetic truth's angles given as a known angle map.
pub fn with_known_angle(mut s: Scene) -> Scene {
    let t = s.truth.clone().expect("a synthetic scene");
    let deg = (0..t.height)
        .flat_map(|y| (0..t.width).map(move |x| (x, y)))
        .map(|(x, y)| t.angle_deg.at(x, y, t.width, t.height) as f32)
        .collect();
    s.angle = AngleKnowledge::Map {
        width: t.width,
        height: t.height,
        deg,
    };
    s
}
