"""GPS side files: ODM's geo.txt and the CSV, read into WGS84 fixes; every bad line refused by its number."""

from __future__ import annotations

import math
import re

import pytest

from workers.gps_file import GPS_FILE_NAMES, gps_file_name, parse_geo_txt, parse_gps_csv, parse_gps_file

R_MERCATOR = 6378137.0  # EPSG:3857's sphere: x = R lon, y = R ln(tan(pi/4 + lat/2)), lon and lat in radians


def mercator(lon: float, lat: float) -> tuple[float, float]:
    return R_MERCATOR * math.radians(lon), R_MERCATOR * math.log(math.tan(math.pi / 4 + math.radians(lat) / 2))


def test_geo_txt_in_lonlat_with_every_optional_column() -> None:
    text = (
        "EPSG:4326\n"
        "# image x y z omega phi kappa horizontal vertical\n"
        "DJI_0001.JPG -95.3700 29.7600\n"
        "DJI_0002.JPG -95.3701 29.7601 61.5  # a comment after the values\n"
        "\n"
        "DJI_0003.JPG -95.3702 29.7602 62.0 0.5 -1.0 90.0\n"
        "DJI_0004.JPG -95.3703 29.7603 63.0 0.5 -1.0 90.0 0.02 0.05 extra fields\n"
    )
    crs, fixes = parse_geo_txt(text)
    assert crs == "EPSG:4326"
    assert [f.name for f in fixes] == ["DJI_0001.JPG", "DJI_0002.JPG", "DJI_0003.JPG", "DJI_0004.JPG"]
    assert [f.line for f in fixes] == [3, 4, 6, 7]
    assert fixes[0].lon == -95.37 and fixes[0].lat == 29.76 and fixes[0].alt is None  # x is the longitude
    assert [f.alt for f in fixes[1:]] == [61.5, 62.0, 63.0]
    assert [f.accuracy_m for f in fixes] == [None, None, None, 0.02]


@pytest.mark.parametrize("crs", ["EPSG:32633", "+proj=utm +zone=33 +datum=WGS84 +units=m +no_defs", "WGS84 UTM 33N"])
def test_projected_geo_txt_is_converted_to_lonlat(crs: str) -> None:
    # On UTM 33N's central meridian (15 E): easting 500000, northing 0.9996 x the WGS84 meridian arc to 45 N
    # (4984944.378 m); at the equator the northing is 0.
    _, fixes = parse_geo_txt(f"{crs}\na.jpg 500000 4982950.400 100\nb.jpg 500000 0 90\n")
    assert [(f.lon, f.lat) for f in fixes] == [
        (pytest.approx(15.0, abs=1e-6), pytest.approx(45.0, abs=1e-6)),
        (pytest.approx(15.0, abs=1e-6), pytest.approx(0.0, abs=1e-6)),
    ]
    assert [f.alt for f in fixes] == [100.0, 90.0]  # heights pass through as the file states them


def test_web_mercator_geo_txt_matches_the_closed_form() -> None:
    truth = [(-95.37, 29.76), (151.2093, -33.8688), (2.3522, 48.8566)]
    lines = "".join(f"f{k}.jpg {x:.4f} {y:.4f} 50\n" for k, (x, y) in enumerate(mercator(*p) for p in truth))
    _, fixes = parse_geo_txt("EPSG:3857\n" + lines)
    for fix, (lon, lat) in zip(fixes, truth, strict=True):
        assert abs(fix.lon - lon) < 1e-6 and abs(fix.lat - lat) < 1e-6


def test_csv_with_and_without_a_header() -> None:
    body = "a.jpg,29.76,-95.37,60.0,1.5\nb.jpg, 29.7601 , -95.3701 ,61\nc.jpg,29.7602,-95.3702,,\n"
    for text, first_line in [("\ufeffname,lat,lon,alt,accuracy\n" + body, 2), (body, 1), ("# log\n" + body, 2)]:
        fixes = parse_gps_csv(text)
        assert [(f.name, f.lat, f.lon, f.alt, f.accuracy_m) for f in fixes] == [
            ("a.jpg", 29.76, -95.37, 60.0, 1.5),
            ("b.jpg", 29.7601, -95.3701, 61.0, None),
            ("c.jpg", 29.7602, -95.3702, None, None),
        ]
        assert fixes[0].line == first_line


def test_the_format_is_told_by_name_then_content() -> None:
    assert gps_file_name("nav.csv", "EPSG:4326\n") == GPS_FILE_NAMES[1]
    assert gps_file_name("nav.txt", "# log\nname,lat,lon,alt\n") == GPS_FILE_NAMES[1]
    assert gps_file_name("geo.txt", "EPSG:4326\na.jpg 1 2\n") == GPS_FILE_NAMES[0]
    assert gps_file_name("nav.txt", "+proj=utm +zone=33 +towgs84=0,0,0\n") == GPS_FILE_NAMES[0]
    parsed = parse_gps_file("gps.csv", "a.jpg,1,2,3\n")
    assert parsed.name == "gps.csv" and parsed.crs == "EPSG:4326" and parsed.fixes[0].lon == 2.0


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "geo.txt is empty"),
        ("# only a comment\n", "geo.txt is empty"),
        ("EPSG:nonsense\na.jpg 1 2\n", "line 1: unknown coordinate system 'EPSG:nonsense'"),
        ("EPSG:5773\na.jpg 1 2\n", "line 1: 'EPSG:5773' is not a horizontal coordinate system"),
        ("WGS84 UTM 61N\na.jpg 1 2\n", "line 1: UTM zone 61 is outside 1..60"),
        ("EPSG:4326\na.jpg 1\n", "line 2: expected 'image_name x y"),
        ("EPSG:4326\na.jpg 1 2 3 4 5\n", "line 2: expected 'image_name x y [z] [omega phi kappa]"),
        ("EPSG:4326\n\na.jpg 1 2 3 4 5 6 7\n", "line 3: expected"),
        ("EPSG:4326\na.jpg east 2\n", "line 2: x 'east' is not a number"),
        ("EPSG:4326\na.jpg 1 nan\n", "line 2: y 'nan' is not a finite number"),
        ("EPSG:4326\na.jpg 1 2 inf\n", "line 2: z 'inf' is not a finite number"),
        ("EPSG:4326\na.jpg 1 2 3 0 x 0\n", "line 2: phi 'x' is not a number"),
        ("EPSG:4326\na.jpg 1 2 3 0 0 0 0 1\n", "line 2: horizontal accuracy 0.0 m is not positive"),
        ("EPSG:4326\na.jpg 1 2 3 0 0 0 1 -1\n", "line 2: vertical accuracy -1.0 m is not positive"),
        ("EPSG:4326\nok.jpg 1 2\na.jpg -95.37 95\n", "line 3: latitude 95.0 is outside -90..90"),
        ("EPSG:4326\na.jpg 500 29.76\n", "line 2: longitude 500.0 is outside -180..180"),
        ("EPSG:32633\na.jpg 1e30 1e30\n", "line 2: a.jpg lies outside the area its coordinate system covers"),
        ("EPSG:4326\na.jpg 1 2\nb.jpg 1 2\n# c\na.jpg 3 4\n", "line 5: a.jpg is listed twice, on lines 2 and 5"),
        ("EPSG:4326\n" + "x" * 300 + " 1 2\n", "line 2: an image name of 300 characters"),
    ],
)
def test_bad_geo_txt_names_the_line(text: str, message: str) -> None:
    with pytest.raises(ValueError, match="^" + re.escape(message)):
        parse_geo_txt(text)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("name,lon,lat,alt\na.jpg,1,2,3\n", "line 1: header 'name,lon,lat,alt' is not name,lat,lon,alt"),
        ("a.jpg,29.76,-95.37\n", "line 1: expected 'name,lat,lon,alt[,accuracy]', got 3 fields"),
        ("a.jpg,29.76,-95.37,1,2,3\n", "line 1: expected 'name,lat,lon,alt[,accuracy]', got 6 fields"),
        ("name,lat,lon,alt\na.jpg,north,-95.37,60\n", "line 2: latitude 'north' is not a number"),
        ("a.jpg,29.76,-95.37,60\nb.jpg,95,-95.37,60\n", "line 2: latitude 95.0 is outside -90..90"),
        ("a.jpg,29.76,-195,60\n", "line 1: longitude -195.0 is outside -180..180"),
        ("a.jpg,29.76,inf,60\n", "line 1: longitude 'inf' is not a finite number"),
        ("a.jpg,29.76,-95.37,1e999\n", "line 1: altitude '1e999' is not a finite number"),
        ("a.jpg,29.76,-95.37,60,-2\n", "line 1: accuracy -2.0 m is not positive"),
        (",29.76,-95.37,60\n", "line 1: the image name is empty"),
        ("a.jpg,1,2,3\n\nb.jpg,1,2,3\na.jpg,1,2,3\n", "line 4: a.jpg is listed twice, on lines 1 and 4"),
    ],
)
def test_bad_csv_names_the_line(text: str, message: str) -> None:
    with pytest.raises(ValueError, match="^" + re.escape(message)):
        parse_gps_csv(text)
