"""The input generation still makes the data that `eval.code_hash.INPUT_VERSION` versions.

Stored runs and cached inputs are kept across any edit of datasets/ that generates the same data (eval/code_hash.py):
that is what lets the input generation be refactored without rerunning every stored run. The price is this test:
a change to what datasets/ generates, at this INPUT_VERSION, fails here. Then bump INPUT_VERSION (every cached
input and stored run is made again, as it must be) and paste the output of `python tests/fingerprints.py` into
`EXPECTED`. Fingerprints: tests/fingerprints.py (each input along the harness's path, at small sizes).
"""
from __future__ import annotations

import pytest

from eval.code_hash import INPUT_VERSION
from fingerprints import cases, matches

#: The INPUT_VERSION these fingerprints belong to.
VERSION = 2
#: {case: {array: [shape, sum of magnitudes, sum, weighted sum]}}, from `python tests/fingerprints.py`.
EXPECTED = {'capture': {'depth': [[4, 32, 32], 501.96387577056885, 501.96387577056885, 28.02709337550236],
             'diffuse': [[4, 32, 32], 210.62359899282455, 210.62359899282455, 11.989521984162941],
             'mask': [[4, 32, 32], 293.0, 293.0, 18.15738230572191],
             'projection': [[4, 4], 5.341573356437182, 0.9371689520327784, -0.9397474874660363],
             'world_to_camera': [[4, 4, 4], 27.270656422444137, -0.9358222275240875, -2.486336852249187]},
 'corrupt density': {'is_outlier': [[1000], 0.0, 0.0, 0.0],
                     'normals': [[1000, 3], 1020.9393004998565, 55.29051626473665, 4.634060739821071],
                     'points': [[1000, 3], 937.543831805644, -770.8901304399224, 8.267396813442089]},
 'corrupt estimated': {'is_outlier': [[3000], 0.0, 0.0, 0.0],
                       'normals': [[3000, 3], 3373.544398151331, 367.0043425015648, 11.450702853494315],
                       'points': [[3000, 3], 2786.3571480125356, -2284.952188434585, 28.453033228059827]},
 'corrupt noise': {'is_outlier': [[3000], 0.0, 0.0, 0.0],
                   'normals': [[3000, 3], 3063.5541463196278, 234.38279918208718, 30.447078408209045],
                   'points': [[3000, 3], 2786.048452536181, -2284.6550563191395, 28.585638988077722]},
 'corrupt nonuniform': {'is_outlier': [[3000], 0.0, 0.0, 0.0],
                        'normals': [[3000, 3], 3107.219400606118, 996.7101144092157, -6.003515758616135],
                        'points': [[3000, 3], 2545.61420099703, -1876.772373669106, 32.193527575071]},
 'corrupt outliers': {'is_outlier': [[3000], 150.0, 150.0, 4.476737170693187],
                      'normals': [[3000, 3], 3137.0757444212213, 214.82335424795747, 22.005246466067742],
                      'points': [[3000, 3], 2802.9672261670166, -2242.682757425977, 29.608338736529774]},
 'corrupt scan': {'camera_index': [[3000], 7143.0, 7143.0, -44.093285119909694],
                  'cameras': [[6, 3], 18.49454398788937, -3.2906204941434813, -0.019121284555022076],
                  'is_outlier': [[3000], 30.0, 30.0, 0.5074210852288596],
                  'normals': [[3000, 3], 3092.696047947742, 547.901029012166, 11.883508080222231],
                  'points': [[3000, 3], 2774.71329906577, -2102.491421335013, 26.645047665504684]},
 'depth noise': {'depth': [[4, 32, 32], 502.13626885414124, 502.13626885414124, 28.019072150037662]},
 'gt flag_box': {'faces': [[658, 3], 364415.0, 364415.0, 1986.7757782711735],
                 'vertices': [[370, 3], 84.04266555939373, -4.334310688136611e-13, -1.1848151493535781]},
 'samples': {'normals': [[3000, 3], 3063.5541463196278, 234.38279918208718, 30.447078408209045],
             'points': [[3000, 3], 2786.3571480125356, -2284.952188434585, 28.453033228059827]},
 'shape bowl': {'faces': [[2496, 3], 4677248.0, 4677248.0, -17121.79311134394],
                'vertices': [[1281, 3], 1984.1358775530562, -939.4356998079581, 6.441970924686133]},
 'shape bracket': {'faces': [[43578, 3], 1423221570.0, 1423221570.0, -443231.2903240046],
                   'vertices': [[21783, 3], 21363.311313011218, 2302.3746264544316, 24.051876589631828]},
 'shape bracket_hose': {'faces': [[42460, 3], 1350542287.0, 1350542287.0, -856258.1229228829],
                        'vertices': [[21246, 3], 20895.121886120935, 2629.8130399033817, 63.51943613310047]},
 'shape csg': {'faces': [[1648, 3], 2015922.0, 2015922.0, -13578.9412589403],
               'vertices': [[816, 3], 1165.6133411377668, 0.0, 8.348225688704291]},
 'shape disc': {'faces': [[1984, 3], 2956160.0, 2956160.0, -18407.930469536856],
                'vertices': [[1025, 3], 683.2373432124919, -3.530509218307998e-14, -12.635292247500473]},
 'shape flag_box': {'faces': [[658, 3], 364415.0, 364415.0, 1986.7757782711735],
                    'vertices': [[370, 3], 549.9074610341908, 534.1923882896313, -7.451082232704714]},
 'shape genus2': {'faces': [[4632, 3], 16043011.0, 16043011.0, -154333.3268279522],
                  'vertices': [[2314, 3], 2565.3162764454373, 0.0, -33.88935948176213]},
 'shape lamp': {'faces': [[1360, 3], 1467608.0, 1467608.0, -942.5653803903633],
                'vertices': [[734, 3], 601.5661223078951, 214.09999999999997, 4.171862415760535]},
 'shape leaf': {'faces': [[1728, 3], 2243072.0, 2243072.0, -21705.95158978224],
                'vertices': [[897, 3], 467.4050032340325, 146.61586276043184, -2.6544804018151766]},
 'shape mobius': {'faces': [[1680, 3], 2416673.0, 2416673.0, -7919.687454851769],
                  'vertices': [[960, 3], 1378.023364426493, -5.684341886080802e-14, -14.350823886393353]},
 'shape mushroom': {'faces': [[1808, 3], 2460258.0, 2460258.0, -29678.994270294254],
                    'vertices': [[931, 3], 797.8660991610909, 365.58615234061017, -3.1007384485762057]},
 'shape open_cylinder': {'faces': [[2944, 3], 6778560.0, 6778560.0, -16267.89363377478],
                         'vertices': [[1536, 3], 1625.2380722476983, -1.1368683772161603e-13, -3.593771268558978]},
 'shape plant': {'faces': [[2304, 3], 4158138.0, 4158138.0, -5404.721614717887],
                 'vertices': [[1224, 3], 826.455741858832, 428.9179208074563, -2.5232033283602173]},
 'shape sphere': {'faces': [[1280, 3], 1234500.0, 1234500.0, -10347.60602263682],
                  'vertices': [[642, 3], 971.288549055219, -1.4210854715202004e-14, -30.363120706100787]},
 'shape tablecloth': {'faces': [[3102, 3], 7664787.0, 7664787.0, -43817.37131730348],
                      'vertices': [[1640, 3], 1586.1322410906694, 218.21451723796156, 7.530219295246951]},
 'shape tank_pipes': {'faces': [[36396, 3], 995831430.0, 995831430.0, -434162.8127111611],
                      'vertices': [[18245, 3], 16626.583922796002, -356.6882607495645, 26.471128154251524]},
 'shape thin_cup': {'faces': [[63936, 3], 3070494728.0, 3070494728.0, -1161829.5170704417],
                    'vertices': [[31970, 3], 32638.272691066875, -5494.412302244437, 61.7394517372051]},
 'shape torus': {'faces': [[2304, 3], 3977856.0, 3977856.0, -9698.878054404773],
                 'vertices': [[1152, 3], 1208.002984098141, -1.1368683772161603e-13, -20.60900001986869]},
 'shape trefoil': {'faces': [[56000, 3], 2351916000.0, 2351916000.0, -1332578.5255621583],
                   'vertices': [[28000, 3], 31553.695446030648, -6.821210263296962e-13, -81.26986987404621]},
 'shape vessel': {'faces': [[36802, 3], 1020481409.0, 1020481409.0, -450196.6334775142],
                  'vertices': [[18487, 3], 11785.051509032324, 962.1507781115683, 55.6277090770773]},
 'shape wavy_sheet': {'faces': [[4084, 3], 13367945.0, 13367945.0, -141939.84598482156],
                      'vertices': [[2183, 3], 2424.373844151898, 22.66857805828738, 7.234685807611703]},
 'shared spot': {'class': 'closed',
                 'faces': [[5856, 3], 25857095.0, 25857095.0, -156182.65492611285],
                 'vertices': [[2930, 3], 2769.176412468839, -2.2737367544323206e-13, -50.686524611661696]}}


#: Tolerance (of the sum of magnitudes) per case: rendered images are rasterised by the machine's OpenGL, whose
#: last bits depend on the driver; a change to the rig, the projection or the shading moves them far more. A
#: simulated scan's hits are open3d's Embree ray casts in float32, whose last bits depend on the CPU's vector
#: units (the same open3d 0.20.0 gave the points' sums 2774.71329906577 on an Intel Xeon and 2774.7132795155667
#: on an AMD EPYC, 7e-9 apart relatively); a change to the cameras, the rays or the noise moves them far more.
RTOL = {"capture": 1e-4, "depth noise": 1e-4, "corrupt scan": 1e-6}


@pytest.fixture(scope="module")
def found():
    return cases()


def test_the_fingerprints_are_those_of_this_input_version():
    assert VERSION == INPUT_VERSION, (f"INPUT_VERSION is {INPUT_VERSION}, these fingerprints are of {VERSION}: "
                                      "paste the output of `python tests/fingerprints.py` into EXPECTED")


def _differs(found: dict, case: str, name: str) -> bool:
    want, got = EXPECTED[case][name], found[case].get(name)
    if got is None or isinstance(want, str):
        return got != want
    return not matches(got, want, RTOL.get(case, 1e-10))


@pytest.mark.parametrize("case", sorted(EXPECTED))
def test_generated_input_is_unchanged(found, case):
    if case not in found:
        pytest.skip(f"{case}: not generated here (no OpenGL for the capture, or ../shared/meshes missing)")
    changed = sorted(name for name in EXPECTED[case] if _differs(found, case, name))
    assert not changed, (f"{case}: {', '.join(changed)} differ from their fingerprint at INPUT_VERSION "
                         f"{INPUT_VERSION}: the input generation changed what it makes. Bump "
                         "eval.code_hash.INPUT_VERSION and paste `python tests/fingerprints.py` into EXPECTED")


def test_every_generated_input_has_a_fingerprint(found):
    assert not sorted(set(found) - set(EXPECTED)), "new cases: paste `python tests/fingerprints.py` into EXPECTED"


def test_the_fingerprint_sees_a_change_of_one_value():
    import numpy as np

    from fingerprints import fingerprint

    a = np.random.default_rng(0).normal(size=(500, 3))
    b = a.copy()
    b[123, 1] += 1e-5
    assert matches(fingerprint(a), fingerprint(a.copy()))
    assert not matches(fingerprint(b), fingerprint(a))
    assert not matches(fingerprint(a[:-1]), fingerprint(a))
