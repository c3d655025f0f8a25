// WGS-84 conversions for the cursor readout: mission NED (m) -> latitude, longitude, altitude.
// The same tangent-plane frame as companion/frames.py (pymap3d.ned2geodetic): NED at the
// mission origin -> ECEF -> geodetic (Bowring's formula, then two Newton steps on latitude).
"use strict";
(function () {
  const A = 6378137.0, F = 1 / 298.257223563, E2 = F * (2 - F), B = A * (1 - F), EP2 = (A * A - B * B) / (B * B);
  const RAD = Math.PI / 180;

  function geodeticToEcef(latDeg, lonDeg, h) {
    const lat = latDeg * RAD, lon = lonDeg * RAD;
    const s = Math.sin(lat), c = Math.cos(lat);
    const n = A / Math.sqrt(1 - E2 * s * s);
    return [(n + h) * c * Math.cos(lon), (n + h) * c * Math.sin(lon), (n * (1 - E2) + h) * s];
  }

  function ecefToGeodetic(x, y, z) {
    const lon = Math.atan2(y, x);
    const p = Math.hypot(x, y);
    const th = Math.atan2(z * A, p * B);
    let lat = Math.atan2(z + EP2 * B * Math.pow(Math.sin(th), 3), p - E2 * A * Math.pow(Math.cos(th), 3));
    let h = 0;
    for (let i = 0; i < 2; i++) {
      const s = Math.sin(lat);
      const n = A / Math.sqrt(1 - E2 * s * s);
      h = Math.abs(Math.cos(lat)) > 1e-9 ? p / Math.cos(lat) - n : Math.abs(z) - B;
      lat = Math.atan2(z, p * (1 - E2 * n / (n + h)));
    }
    return [lat / RAD, lon / RAD, h];
  }

  // ned: [north, east, down] m at origin {lat_deg, lon_deg, alt_m} -> [lat_deg, lon_deg, alt_m]
  function nedToGeodetic(n, e, d, origin) {
    const lat0 = origin.lat_deg * RAD, lon0 = origin.lon_deg * RAD;
    const [x0, y0, z0] = geodeticToEcef(origin.lat_deg, origin.lon_deg, origin.alt_m);
    const u = -d;
    const sl = Math.sin(lat0), cl = Math.cos(lat0), so = Math.sin(lon0), co = Math.cos(lon0);
    const dx = -so * e - sl * co * n + cl * co * u;
    const dy = co * e - sl * so * n + cl * so * u;
    const dz = cl * n + sl * u;
    return ecefToGeodetic(x0 + dx, y0 + dy, z0 + dz);
  }

  function formatLatLon(lat, lon) {
    const ns = lat >= 0 ? "N" : "S", ew = lon >= 0 ? "E" : "W";
    return `${Math.abs(lat).toFixed(7)}°${ns} ${Math.abs(lon).toFixed(7)}°${ew}`;
  }

  window.SDGeo = { nedToGeodetic, geodeticToEcef, ecefToGeodetic, formatLatLon };
})();
