//! The operator console: a page at `/` and its files under `/console/`, compiled into the binary
//! (no Node at run time). The page uses only the documented REST API; its files need no token
//! (they hold no data), the API calls it makes do.

use axum::extract::Path;
use axum::http::{HeaderValue, header};
use axum::response::{IntoResponse, Response};
use depthmill_proto::ErrorCode;

use crate::app::ApiError;

/// Every file of the console: path under `/console/`, media type, bytes.
const FILES: &[(&str, &str, &[u8])] = &[
    ("index.html", "text/html; charset=utf-8", include_bytes!("../../console/index.html")),
    ("app.js", "text/javascript; charset=utf-8", include_bytes!("../../console/app.js")),
    ("style.css", "text/css; charset=utf-8", include_bytes!("../../console/style.css")),
    (
        "vendor/three.module.js",
        "text/javascript; charset=utf-8",
        include_bytes!("../../console/vendor/three.module.js"),
    ),
    (
        "vendor/three.core.js",
        "text/javascript; charset=utf-8",
        include_bytes!("../../console/vendor/three.core.js"),
    ),
    (
        "vendor/OrbitControls.js",
        "text/javascript; charset=utf-8",
        include_bytes!("../../console/vendor/OrbitControls.js"),
    ),
    (
        "vendor/PLYLoader.js",
        "text/javascript; charset=utf-8",
        include_bytes!("../../console/vendor/PLYLoader.js"),
    ),
    (
        "vendor/uPlot.esm.js",
        "text/javascript; charset=utf-8",
        include_bytes!("../../console/vendor/uPlot.esm.js"),
    ),
    ("vendor/uPlot.min.css", "text/css; charset=utf-8", include_bytes!("../../console/vendor/uPlot.min.css")),
    (
        "vendor/LICENSE-three.txt",
        "text/plain; charset=utf-8",
        include_bytes!("../../console/vendor/LICENSE-three.txt"),
    ),
    (
        "vendor/LICENSE-uplot.txt",
        "text/plain; charset=utf-8",
        include_bytes!("../../console/vendor/LICENSE-uplot.txt"),
    ),
];

fn file(path: &str) -> Result<Response, ApiError> {
    let (_, media_type, bytes) = FILES
        .iter()
        .find(|(p, _, _)| *p == path)
        .ok_or_else(|| ApiError::new(ErrorCode::NotFound, format!("no console file {path}")))?;
    // The page and the app change with the server; the vendored libraries only with their version.
    let cache = if path.starts_with("vendor/") { "public, max-age=86400" } else { "no-cache" };
    Ok((
        [
            (header::CONTENT_TYPE, HeaderValue::from_static(media_type)),
            (header::CACHE_CONTROL, HeaderValue::from_static(cache)),
            (header::X_CONTENT_TYPE_OPTIONS, HeaderValue::from_static("nosniff")),
        ],
        *bytes,
    )
        .into_response())
}

/// `GET /`: the console's page.
pub(super) async fn index() -> Result<Response, ApiError> {
    file("index.html")
}

/// `GET /console/{path}`: a file of the console.
pub(super) async fn asset(Path(path): Path<String>) -> Result<Response, ApiError> {
    file(&path)
}

#[cfg(test)]
mod tests {
    use sha2::{Digest, Sha256};

    use super::*;

    /// The vendored libraries are the files their npm packages publish (vendor/README.md).
    #[test]
    fn vendor_files_are_the_published_ones() {
        let expected = [
            ("vendor/three.module.js", "104f56145899722094556490d787aae0617cc2fc3382f31df02d724ea1aee341"),
            ("vendor/three.core.js", "613e370f76638fdef83926642bf256dc9615684922de1ce1f63a8583e5d78578"),
            ("vendor/OrbitControls.js", "e7fca2fe9e7670a828af9b28084669a5909445b7f36f1f26cee9bf8f2961c32c"),
            ("vendor/PLYLoader.js", "751ff866f793ba1fc9181425748d88b7f9234c6e9983386fdaf2e664221340f2"),
            ("vendor/uPlot.esm.js", "5dd9b3281aa64b461b42d9945f6adb2649d346502b12281a9ae0d46599a80eba"),
            ("vendor/uPlot.min.css", "df630c6a8d6f8eeaff264b50f73ce5b114f646ffd9a0bb74f049b0a00135fa04"),
        ];
        for (path, sha) in expected {
            let (_, _, bytes) = FILES.iter().find(|(p, _, _)| *p == path).expect(path);
            assert_eq!(hex::encode(Sha256::digest(bytes)), sha, "{path}");
        }
    }

    /// The page loads only files the server has.
    #[test]
    fn every_file_the_page_names_is_served() {
        let page = std::str::from_utf8(FILES[0].2).expect("utf-8");
        let mut named = 0;
        for part in page.split("\"/console/").skip(1) {
            let path = part.split('"').next().unwrap_or_default();
            assert!(FILES.iter().any(|(p, _, _)| *p == path), "{path} is not served");
            named += 1;
        }
        assert!(named >= 7, "{named} files named");
        assert!(file("nope.js").is_err());
    }
}
