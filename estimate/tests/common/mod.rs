//! What the parity tests share: where the fetched graphs are, or a loud skip.

use std::path::PathBuf;

use lifegom_estimate::graphs;

/// The graphs folder, or `None` (after saying so) when the test must skip.
pub fn graphs_dir() -> Option<PathBuf> {
    let dir = std::env::var_os("LIFEGOM_WEIGHTS").map(PathBuf::from);
    let missing = dir.as_ref().map_or(3, |d| graphs::missing(d).len());
    if missing == 0 {
        return dir;
    }
    assert!(
        std::env::var_os("LIFEGOM_REQUIRE_WEIGHTS").is_none(),
        "LIFEGOM_REQUIRE_WEIGHTS is set but $LIFEGOM_WEIGHTS ({dir:?}) lacks {missing} of the \
         3 person graphs: run `lifegom-weights fetch --out DIR`"
    );
    eprintln!(
        "PARITY TEST SKIPPED: set LIFEGOM_WEIGHTS to a folder filled by `lifegom-weights \
         fetch` to check the MediaPipe graphs against TensorFlow Lite and MediaPipe's pipeline"
    );
    None
}
