/* The same three products as src/main.rs through cblas_sgemm (Debian's OpenBLAS; run with
 * OPENBLAS_NUM_THREADS=2): median GFLOP/s of 15 calls per product and shape. */
#include <cblas.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
static double now(){struct timespec t;clock_gettime(CLOCK_MONOTONIC,&t);return t.tv_sec+t.tv_nsec*1e-9;}
static float* rnd(size_t n){float*a=malloc(n*4);for(size_t i=0;i<n;i++)a[i]=rand()/(float)RAND_MAX-0.5f;return a;}
static double med(double*v,int n){for(int i=0;i<n;i++)for(int j=i+1;j<n;j++)if(v[j]<v[i]){double t=v[i];v[i]=v[j];v[j]=t;}return v[n/2];}
int main(){
  int shapes[][3]={{4096,40,512},{4096,512,512},{4000,40,256},{4000,256,256},{24000,512,512}};
  for(int s=0;s<5;s++){int rows=shapes[s][0],in=shapes[s][1],out=shapes[s][2];
    float*x=rnd((size_t)rows*in),*w=rnd((size_t)in*out),*y=rnd((size_t)rows*out),*dz=rnd((size_t)rows*out),*dw=rnd((size_t)in*out),*dx=rnd((size_t)rows*in);
    double tf[15],tw[15],tx[15];
    for(int r=0;r<15;r++){double t=now();
      cblas_sgemm(CblasRowMajor,CblasNoTrans,CblasNoTrans,rows,out,in,1,x,in,w,out,0,y,out);tf[r]=now()-t;t=now();
      cblas_sgemm(CblasRowMajor,CblasTrans,CblasNoTrans,in,out,rows,1,x,in,dz,out,0,dw,out);tw[r]=now()-t;t=now();
      cblas_sgemm(CblasRowMajor,CblasNoTrans,CblasTrans,rows,in,out,1,dz,out,w,out,0,dx,in);tx[r]=now()-t;}
    double g=2.0*rows*in*out/1e9;
    printf("%5d x %3d -> %3d: y=x.w %6.1f  dw=xT.dz %6.1f  dx=dz.wT %6.1f GFLOP/s\n",rows,in,out,g/med(tf,15),g/med(tw,15),g/med(tx,15));}
}
