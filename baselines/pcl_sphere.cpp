// PCL's sphere segmentation (pcl::SACSegmentation, SACMODEL_SPHERE, RANSAC) over clouds read from stdin:
// the peer that `spherebench pcl-bench` times beside the 3D detector (``baselines/pcl_peer.py`` builds and drives it).
//
// usage: pcl_sphere RADIUS_M TOLERANCE_M THRESHOLD_M MAX_ITERATIONS SAMPLES_MAX_DIST_M
//   stdin: clouds, each a little-endian uint32 point count N then N x 3 float32 (metres, camera frame)
//   stdout: one line per cloud, written once it is segmented:
//     ms cx cy cz r inliers   (ms: the segmentation's wall time, the search tree's build included;
//                              inliers 0 and the rest nan where no sphere was found)
// SAMPLES_MAX_DIST_M > 0: local sampling (a sample's other points within that distance of its first,
// found through a k-d tree); 0: samples drawn from the whole cloud. The model's random generator is
// PCL's fixed seed, so the same clouds give the same spheres.
#include <pcl/ModelCoefficients.h>
#include <pcl/point_types.h>
#include <pcl/search/kdtree.h>
#include <pcl/segmentation/sac_segmentation.h>

#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <iostream>
#include <limits>

int main(int argc, char** argv) {
  if (argc != 6) {
    std::fprintf(stderr, "usage: %s RADIUS_M TOLERANCE_M THRESHOLD_M MAX_ITERATIONS SAMPLES_MAX_DIST_M\n", argv[0]);
    return 2;
  }
  const double radius = std::atof(argv[1]), tolerance = std::atof(argv[2]), threshold = std::atof(argv[3]);
  const int iterations = std::atoi(argv[4]);
  const double samples_max_dist = std::atof(argv[5]);
  std::uint32_t n = 0;
  while (std::fread(&n, sizeof(n), 1, stdin) == 1) {
    pcl::PointCloud<pcl::PointXYZ>::Ptr cloud(new pcl::PointCloud<pcl::PointXYZ>);
    cloud->resize(n);
    for (std::uint32_t i = 0; i < n; ++i) {
      float xyz[3];
      if (std::fread(xyz, sizeof(float), 3, stdin) != 3) {
        std::fprintf(stderr, "pcl_sphere: a cloud ended after %u of its %u points\n", i, n);
        return 1;
      }
      (*cloud)[i].x = xyz[0];
      (*cloud)[i].y = xyz[1];
      (*cloud)[i].z = xyz[2];
    }
    const auto t0 = std::chrono::steady_clock::now();
    pcl::SACSegmentation<pcl::PointXYZ> seg;
    seg.setOptimizeCoefficients(true);
    seg.setModelType(pcl::SACMODEL_SPHERE);
    seg.setMethodType(pcl::SAC_RANSAC);
    seg.setDistanceThreshold(threshold);
    seg.setMaxIterations(iterations);
    seg.setRadiusLimits(radius - tolerance, radius + tolerance);
    seg.setInputCloud(cloud);
    if (samples_max_dist > 0) {
      pcl::search::KdTree<pcl::PointXYZ>::Ptr tree(new pcl::search::KdTree<pcl::PointXYZ>);
      tree->setInputCloud(cloud);
      seg.setSamplesMaxDist(samples_max_dist, tree);
    }
    pcl::PointIndices inliers;
    pcl::ModelCoefficients sphere;
    seg.segment(inliers, sphere);
    const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    const double nan = std::numeric_limits<double>::quiet_NaN();
    const bool found = !inliers.indices.empty() && sphere.values.size() == 4;
    std::printf("%.6f %.9g %.9g %.9g %.9g %zu\n", ms, found ? sphere.values[0] : nan, found ? sphere.values[1] : nan,
                found ? sphere.values[2] : nan, found ? sphere.values[3] : nan, inliers.indices.size());
    std::fflush(stdout);
  }
  return 0;
}
