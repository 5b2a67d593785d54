/* omnid libHDU: a line segment between two points (docs/HDAPI.md, libHDU). Header-only,
 * C++ only (empty in C). */
#ifndef OMNID_HDU_LINE_SEGMENT_H
#define OMNID_HDU_LINE_SEGMENT_H

#ifdef __cplusplus
#include <HDU/hduVector.h>

template <typename T> class hduLineSegment {
public:
    typedef hduVector3D<T> Point;

    hduLineSegment() {}
    hduLineSegment(const Point &start, const Point &end) : start_(start), end_(end) {}

    const Point &getStartPoint() const { return start_; }
    const Point &getEndPoint() const { return end_; }
    void setStartPoint(const Point &p) { start_ = p; }
    void setEndPoint(const Point &p) { end_ = p; }

    /* end - start. */
    Point direction() const { return end_ - start_; }
    T length() const { return direction().magnitude(); }
    /* The point at parameter t: start at 0, end at 1. */
    Point pointAt(T t) const { return start_ + direction() * t; }

    /* The point of the segment nearest to `p`; `t` receives its parameter (0 at start,
     * 1 at end). A segment of length zero projects everything onto its start. */
    Point projectPoint(const Point &p, T &t) const
    {
        Point d = direction();
        T dd = d.dotProduct(d);
        t = dd > T(0) ? (p - start_).dotProduct(d) / dd : T(0);
        if (t < T(0))
            t = T(0);
        else if (t > T(1))
            t = T(1);
        return pointAt(t);
    }
    Point projectPoint(const Point &p) const { T t; return projectPoint(p, t); }

    /* Distance from `p` to the nearest point of the segment. */
    T distance(const Point &p) const { return (p - projectPoint(p)).magnitude(); }
    T distanceSqr(const Point &p) const { return (p - projectPoint(p)).magnitudeSquared(); }

private:
    Point start_, end_;
};

typedef hduLineSegment<double> hduLineSegmentd;
typedef hduLineSegment<float> hduLineSegmentf;

#endif
#endif
